"""The training step after marching, captured as a CUDA graph and replayed.

A step on the GPU is host-bound: ~300 small launches (hash grid, the MLPs' forward and double
backward, the render and projection kernels, the losses, backward, Adam) cost more host time
than the GPU needs to run them. :meth:`Trainer.compute` (the field, compositing, losses,
backward and the guarded Adam update) reads nothing from the host, so it can be recorded once
and replayed as one graph launch, given that

- its inputs live in fixed buffers: the rays (the ray count is rounded to 8 values per octave),
  the uniform eikonal points, and the march's samples padded to a capacity rounded up to 16
  values per octave; a 0/1 ``valid`` vector keeps the padding out of the eikonal and curvature
  means (padded samples belong to no ray, so compositing never sees them);
- the values that change from step to step are on the device: the learning rates and bias
  corrections (``Adam.prepare_device_step``), the sharpness floor and the number of active hash
  levels (``SDFField.enable_device_schedule``), the NeuS cos-anneal ratio (``Trainer.cos_dev``), the
  mask loss's weight (``Trainer.mask_w_dev``, ``loss.mask_weight_start``), the background prior's
  ramped-in weight (``Trainer.bg_w_dev``), the decoded / swept surface prior's faded weight
  (``Trainer.prior_w_dev``; its points drawn with the default CUDA generator in the graph);
- nothing else changes: steps with pose / blur / water corrections, or a step count that differs
  inside a parameter group run eagerly (:meth:`StepGraphs.eligible`).

A step whose sample count is not read back (a *capped* step: its capacity planned from the last
count read back, :meth:`StepGraphs.capped`) also replays the ray draw and the march as a second,
small graph per key (:meth:`StepGraphs.drawn`: the draw with the default CUDA generator, the
copies into the fixed inputs, the capped march), so the host launches two graphs and a few fills
per step. It is recorded on the key's first capped step and retired when what the draw reads is
replaced (:data:`DRAW_FIELDS`, :meth:`StepGraphs.draw_token`).

One graph per (ray count, sample capacity, loss terms). A key is captured when two steps in a
row have it (a key seen once runs eagerly and is never recorded; with graphs the trainer's ray
count jumps straight to a far target, so it does not pass through several keys after the occupancy
grid's first update): on the run's first capture that second step runs eagerly on a side stream
(its update, warming that stream's cuBLAS handle and autograd) and then records the graph; later
captures record first and replay the new graph for that step's update. A failed capture turns the
graphs off for the run with one printed line; training goes on eagerly. ``run.cuda_graph=off``
keeps every step eager (the tested reference; tests/test_graphstep.py compares the two).
"""
from __future__ import annotations

import collections
import math
import time

import torch

from fastneus.field.renderer import march_samples_capped
from fastneus.train.rays import RayBank

MAX_GRAPHS = 8  # least recently used graphs are dropped past this (each keeps its activations)
# the adaptive ray count drifts as the surface sharpens: within 25 % of the captured count the
# graph is kept (12 % captured 17 graphs in a 10-s rock run, 25 % 12; samples per step stay within
# the range the adaptive count itself spans in a few steps)
RAY_SLACK = 0.25
# a capped step (no host sync) plans its capacity at least this far above the last count read back
# (scaled to its ray count): the count drifts by a few % per step, and a step past its capacity is
# skipped. Below the 5 % (+ rounding) that a counted step's new capacity gets, so those graphs serve.
CAP_MARGIN = 1.04
MIN_FREE = 0.35  # ... and while less than this share of the GPU's memory is free (_make_room)
# what a ray draw reads of the bank: a recorded draw graph reads these tensors where it was recorded,
# so one that is replaced (the halo's weights at 30 % of a run, new background flags) retires it
DRAW_FIELDS = ("rgb", "lut", "mask", "mask_core", "bg", "bg_soft", "fg", "cdf", "offset", "wh", "kinv", "rot", "origin", "port")


def ray_bucket(n: int) -> int:
    """``n`` rounded to one of 8 values per octave (>= 8)."""
    n = max(8, int(n))
    q = 1 << max(0, n.bit_length() - 4)
    return max(q, int(round(n / q)) * q)


def sample_bucket(s: int) -> int:
    """The smallest of 16 values per octave that holds ``s`` samples (>= s)."""
    s = max(16, int(s))
    q = 1 << max(0, s.bit_length() - 5)
    return int(math.ceil(s / q)) * q


class _Entry:
    """Static buffers of one captured step and its graph.

    ``batch``: the ray batch's tensors at their step shapes (rays [R, ...], pixels [R / sub, ...]);
    ``xr`` [E, 3] uniform points; ``smp``: offsets, counts [R] int32, t0, t1 [C] float32 and
    ray_index [C] int32 padded to the capacity C (``n_samples`` = C); ``valid`` [C + E] 0/1 (the
    live samples, then the uniform points, which are always live).
    """

    def __init__(self, batch: dict, xr: torch.Tensor, capacity: int, shared: bool = False):
        dev = xr.device
        n = batch["origins"].shape[0]
        # shared: batch and xr are already fixed buffers (StepGraphs.inputs), filled before the march
        self.batch = dict(batch) if shared else {k: v.clone() for k, v in batch.items()}
        self.xr = xr if shared else xr.clone()
        self.capacity = capacity
        self.smp = {"offsets": torch.zeros(n, dtype=torch.int32, device=dev),
                    "counts": torch.zeros(n, dtype=torch.int32, device=dev),
                    "t0": torch.zeros(capacity, dtype=torch.float32, device=dev),
                    "t1": torch.zeros(capacity, dtype=torch.float32, device=dev),
                    "ray_index": torch.zeros(capacity, dtype=torch.int32, device=dev),
                    "n_samples": capacity}
        self.valid = torch.ones(capacity + xr.shape[0], device=dev)
        self._index = torch.arange(capacity, dtype=torch.int32, device=dev)
        self._live = torch.zeros(capacity, dtype=torch.bool, device=dev)
        # the capped march's unclamped sample count (0 after a load: those steps always fit) and
        # whether it fits the capacity (read by the update's guard when the graph replays)
        self.total = torch.zeros(1, dtype=torch.int32, device=dev)
        self.fits = torch.ones(1, dtype=torch.bool, device=dev)
        self.graph: torch.cuda.CUDAGraph | None = None
        self.rec: dict | None = None
        self.draw: tuple | None = None  # (draw token, graph): the rays drawn and marched into these buffers

    def buffers(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """t0, t1, ray_index [C]: where the march writes this step's samples (``march_samples(out=)``)."""
        return self.smp["t0"], self.smp["t1"], self.smp["ray_index"]

    def capped_buffers(self) -> tuple:
        """offsets, counts [R], total [1], t0, t1, ray_index [C]: the capped march's outputs
        (:func:`~fastneus.field.renderer.march_samples_capped`), all read by the graph."""
        return (self.smp["offsets"], self.smp["counts"], self.total, *self.buffers())

    def load(self, batch: dict, xr: torch.Tensor, smp: dict) -> None:
        """Copy this step's inputs in (device-to-device copies: no host sync). Samples the march
        wrote into :meth:`buffers` stay where they are; others are copied and the padding zeroed.
        The padding past the live samples may hold earlier steps' samples: they are finite,
        belong to no ray's span and are out of ``valid``, so they add nothing to the loss or
        the gradients."""
        for k, v in batch.items():
            if v.data_ptr() != self.batch[k].data_ptr():
                self.batch[k].copy_(v)
        if xr.data_ptr() != self.xr.data_ptr():
            self.xr.copy_(xr)
        for k in ("offsets", "counts"):
            self.smp[k].copy_(smp[k])
        self.total.zero_()  # this step's samples were counted on the host: they fit
        if smp["t0"].data_ptr() != self.smp["t0"].data_ptr():
            s = smp["n_samples"]
            for k in ("t0", "t1", "ray_index"):
                self.smp[k][:s].copy_(smp[k])
                self.smp[k][s:].zero_()

    def mark_live(self) -> None:
        """``valid[:C]``: 1 before the last ray's end (``offsets[-1] + counts[-1]``, the live
        sample count), 0 on the padding; ``fits``: the capped march's count within the capacity.
        Read from the loaded offsets on the device, so a captured graph does it when it replays
        (no fill per step outside it)."""
        total = self.smp["offsets"][-1:] + self.smp["counts"][-1:]
        torch.lt(self._index, total, out=self._live)
        self.valid[:self.capacity].copy_(self._live)
        torch.le(self.total, self.capacity, out=self.fits)


class StepGraphs:
    """Captured training steps of one :class:`~fastneus.train.trainer.Trainer` (CUDA only).

    Args:
        trainer: the trainer; its field switches to the device-side schedule.
        console: where the one-line notice of a failed capture goes (None: nowhere).
    """

    _pending: tuple | None = None  # the last step's key when it ran eagerly (not captured)
    _planned: tuple | None = None  # (key, entry, sample count) decided in this step's march (march_out)
    _last: tuple | None = None  # (samples, rays) of the last step whose count is known on the host
    _lag: dict | None = None  # the capped steps' count read back (pinned host int, event)
    unsynced = 0  # replays planned without the march's host sync (capped)
    drawn_steps = 0  # ... of which the draw and the march replayed a graph too (drawn)
    draws_on = True  # recorded draw graphs (off for the run after a failed capture)

    def __init__(self, trainer, console=None):
        self.device = trainer.device
        self.side = torch.cuda.Stream(self.device)
        self.cache: collections.OrderedDict = collections.OrderedDict()
        self.enabled = True
        self.console = console
        self.captured = self.replayed = self.eager = self.evicted = 0
        self.eager_reasons: dict[str, int] = {}  # eager steps by why (run.json: cuda_graphs.eager_reasons)
        self.captures: list[dict] = []  # each capture's step, key sizes and host seconds (run.json)
        self._inputs: dict = {}  # batch layout -> (batch, xr) fixed buffers (inputs)
        self._drawn: dict = {}  # ray count -> (batch, xr) buffers of its last eager draw, its draw token
        trainer.field.enable_device_schedule()
        trainer.cos_dev = torch.ones((1,), device=self.device)  # the NeuS cos-anneal ratio, filled per step
        # the mask loss's weight: filled per step while loss.mask_start changes it
        trainer.mask_w_dev = torch.full((), trainer.mask_weight_at(0.0), device=self.device)
        # the background prior's weight, ramped in per step (losses.background_ramp)
        trainer.bg_w_dev = torch.full((), trainer.bg_weight, device=self.device)
        # the surface prior's weight, faded per step (losses.prior_fade; the one-shot's whole run)
        trainer.prior_w_dev = torch.zeros((), device=self.device)

    def ineligible(self, tr, p: float) -> str | None:
        """Why this step's compute part cannot replay a graph (None: it can): a value in it
        changes from step to step on the host, or a part of it is not captured."""
        c = tr.cfg
        if not self.enabled:
            return "capture failed"
        if tr.rig.active:
            return "rig corrections"
        if not isinstance(tr.bank, RayBank):
            return "multi-shot bank"
        # the curvature taps' and finite differences' step follows the finest active level
        taps = c.loss.curvature_weight > 0 or tr.field.sdf_grad == "fd"
        if taps and tr.field.active_levels < tr.field.hashgrid.levels:
            return "coarse-to-fine taps"
        if not tr.opt.uniform_steps():
            return "optimizer steps differ"
        return None

    def eligible(self, tr, p: float) -> bool:
        """Whether this step's compute part is the same graph as any other step's with its key."""
        why = self.ineligible(tr, p)
        if why is not None:
            self._eager_step(why)
        return why is None

    def _eager_step(self, why: str) -> None:
        self.eager += 1
        self.eager_reasons[why] = self.eager_reasons.get(why, 0) + 1

    def _key(self, tr, batch: dict, capacity: int, p: float) -> tuple:
        return (batch["origins"].shape[0], capacity, *tr.photo_priors(p), tr.prior_on(p), tuple(sorted(batch)))

    def ray_count(self, n: int) -> int:
        """The ray count of this step: the last one while ``n`` stays within :data:`RAY_SLACK` of
        it (so the adaptive count does not hop between graphs), else ``n`` rounded
        (:func:`ray_bucket`)."""
        last = getattr(self, "_rays", None)
        if last is None or abs(n - last) > RAY_SLACK * last:
            self._rays = ray_bucket(n)
        return self._rays

    def _capacity(self, tr, batch: dict, s: int, p: float) -> int:
        """The smallest cached capacity for this key that holds ``s`` samples with at most 20 %
        padding, else a new one 5 % above ``s`` (the count jitters by a few % per step)."""
        rest = self._key(tr, batch, 0, p)
        keys = list(self.cache) + ([self._pending] if self._pending is not None else [])
        fits = [k[1] for k in keys if k[0] == rest[0] and s <= k[1] <= 1.2 * s and k[2:] == rest[2:]]
        return min(fits) if fits else sample_bucket(int(s * 1.05) + 1)

    def inputs(self, batch: dict, xr: torch.Tensor, drawn: tuple | None = None) -> tuple[dict, torch.Tensor]:
        """This step's ray batch and uniform points copied into fixed buffers, one set per
        batch layout (ray count, keys, shapes) shared by every graph of it, before the march:
        the copies run while the device still works on the last step, not between the count
        read and the replay (10 copies: 0.2 ms of idle device per step on an H200). The step
        then uses the returned tensors (same values). ``drawn``: (ray count, :meth:`draw_token`)
        of this draw, remembered so that a later step of that ray count can replay a recorded
        draw into the same buffers (:meth:`drawn`)."""
        sig = (tuple((k, tuple(v.shape), v.dtype) for k, v in sorted(batch.items())), tuple(xr.shape))
        bufs = self._inputs.get(sig)
        if bufs is None:  # kept for the run: a graph reads them where it was recorded
            bufs = self._inputs[sig] = ({k: torch.empty_like(v) for k, v in batch.items()}, torch.empty_like(xr))
        for k, v in batch.items():
            bufs[0][k].copy_(v)
        bufs[1].copy_(xr)
        if drawn is not None:
            self._drawn[drawn[0]] = ((dict(bufs[0]), bufs[1]), drawn[1])
        return dict(bufs[0]), bufs[1]

    @staticmethod
    def draw_token(tr) -> tuple:
        """What a recorded draw of ``tr``'s rays depends on beyond its ray count: the bank's tensors
        (:data:`DRAW_FIELDS`, by identity), the rays per pixel and the lens blur they spread over,
        the rig's pose switch and the occupancy grid's tensors the march reads. A draw graph whose
        token differs from the trainer's is not replayed (:meth:`same_draw`)."""
        b = tr.bank
        return (*(getattr(b, k, None) for k in DRAW_FIELDS), tr.blur_sub, float(tr.camera_blur) if tr.blur_sub > 1 else 0.0,
                bool(getattr(tr.rig, "pose_on", False)), tr.grid.bits, tr.grid.stop)

    @staticmethod
    def same_draw(a: tuple, b: tuple) -> bool:
        """Whether two :meth:`draw_token` values are the same draw: the same tensor objects (not
        equal values: a graph reads the memory it was recorded with), the same plain values."""
        return len(a) == len(b) and all(x is y if isinstance(x, torch.Tensor) or isinstance(y, torch.Tensor) else x == y
                                        for x, y in zip(a, b))

    def drawn(self, tr, n: int, p: float) -> tuple | None:
        """A capped step (:meth:`capped`) whose ray draw and march replay one recorded graph.

        Given the ray count ``n``: the buffers of the last eager draw of ``n`` rays, the same draw
        token as now, and a captured compute graph for the planned key that reads those buffers,
        the draw graph (recorded on first use: the draw with the default CUDA generator, the
        copies into the input buffers, the capped march into the entry's sample buffers) is
        replayed. Returns (key, entry) for :meth:`run_capped`, or None: the step draws eagerly.
        """
        got = self._drawn.get(n) if self.draws_on else None
        # (a flat port's refraction loops over the frames on the host: never a draw graph, no token built)
        if got is None or getattr(tr.bank, "port", None) is not None:
            return None
        (batch, xr), token = got
        now = self.draw_token(tr)
        if not self.same_draw(token, now):
            return None
        est = self._estimate(n)
        if est is None:
            return None
        key, e = self._plan(tr, batch, xr, est, p, create=False)
        if e is None or e.graph is None or e.batch["origins"] is not batch["origins"] or e.xr is not xr:
            return None
        if e.draw is None or not self.same_draw(e.draw[0], now):
            e.draw = None
            g = self._record_draw(tr, n, e)
            if g is None:
                return None
            e.draw = (now, g)
        e.draw[1].replay()
        self.drawn_steps += 1
        return key, e

    def _record_draw(self, tr, n: int, e: _Entry):
        """Record ``e``'s draw graph (nothing runs: the caller replays it). None after a failed capture,
        which turns the draw graphs off for the run with one printed line (the compute graphs stay)."""
        t0 = time.perf_counter()
        cur = torch.cuda.current_stream(self.device)
        self.side.wait_stream(cur)
        g = torch.cuda.CUDAGraph()
        try:
            with torch.cuda.graph(g, stream=self.side):
                batch, xr = tr.draw(n, None)  # the default generator: torch registers it with every capture
                if set(batch) != set(e.batch):
                    raise ValueError(f"the draw's fields {sorted(batch)} are not the buffers' {sorted(e.batch)}")
                for k, v in batch.items():
                    e.batch[k].copy_(v)
                e.xr.copy_(xr)
                march_samples_capped(tr.grid.bits, tr.grid.resolution, e.batch["origins"], e.batch["dirs"], tr.cfg,
                                     e.capped_buffers(), stop=tr.grid.stop)
        except Exception as err:  # noqa: BLE001 - a failed capture falls back to eager draws
            self.draws_on = False
            if self.console is not None:
                self.console.print(f"CUDA graph of the ray draw failed ({type(err).__name__}: "
                                   f"{str(err).splitlines()[0][:120]}); rays are drawn eagerly")
            return None
        finally:
            cur.wait_stream(self.side)
        self.captures.append({"step": tr.step, "rays": n, "capacity": e.capacity, "draw": True,
                              "seconds": round(time.perf_counter() - t0, 4)})
        return g

    def _from_inputs(self, batch: dict) -> bool:
        """Whether ``batch`` is one of :meth:`inputs`' fixed buffer sets (an entry keeps those)."""
        return any(batch["origins"] is b["origins"] for b, _ in getattr(self, "_inputs", {}).values())

    def march_out(self, tr, batch: dict, xr: torch.Tensor, p: float):
        """The ``out`` argument of this step's :func:`~fastneus.field.renderer.march_samples`:
        given the sample count (read after the march's count pass), the step's key is decided
        and a step that replays or records a graph gets its entry's fixed sample buffers to
        write into, so nothing is copied into them between the count read and the replay (the
        device idles while the host queues that work)."""

        def take(total: int):
            if total <= 0:
                return None
            key, e = self._plan(tr, batch, xr, total, p)
            self._planned = (key, e, total)
            return None if e is None else e.buffers()

        return take

    def _plan(self, tr, batch: dict, xr: torch.Tensor, s: int, p: float,
              create: bool = True) -> tuple[tuple, _Entry | None]:
        """This step's key for ``s`` samples and its entry (with ``create``, made for a key seen on
        the step before), or None: a key not seen on the step before runs one eager step."""
        capacity = self._capacity(tr, batch, s, p)
        key = self._key(tr, batch, capacity, p)
        e = self.cache.get(key)
        if e is None and create and key == self._pending:
            self._make_room()
            e = _Entry(batch, xr, capacity, shared=self._from_inputs(batch))
            self.cache[key] = e
            while len(self.cache) > MAX_GRAPHS:
                self.cache.popitem(last=False)
        return key, e

    def step(self, tr, batch: dict, xr: torch.Tensor, smp: dict, p: float) -> dict | None:
        """Run this step's compute part: replay its graph, or run it eagerly and capture it."""
        tr.fill_step_scalars(p)  # read at replay (fills: no host sync)
        planned, self._planned = self._planned, None
        self._last = (smp["n_samples"], batch["origins"].shape[0])  # counted on the host: the estimate's base
        if planned is not None and planned[2] == smp["n_samples"]:
            key, e = planned[:2]
        else:  # the march was not given march_out
            key, e = self._plan(tr, batch, xr, smp["n_samples"], p)
        if e is None:
            # a key not seen on the step before: one eager step, captured only if the next step
            # repeats it. After the occupancy grid's first update the adaptive ray count climbs
            # through ~8 buckets in as many steps, and each was captured (30-50 ms of host time)
            # and never replayed: ~0.3 s of a 3-s budget (H100, perf note 21)
            self._pending = key
            self._eager_step("new key (rays, capacity)")
            return tr.compute(batch, xr, smp, p)
        if key == self._pending:
            self._pending = None
        tr.opt.prepare_device_step()
        self.cache.move_to_end(key)
        e.load(batch, xr, smp)
        if e.graph is not None:
            e.graph.replay()
            self.replayed += 1
            return dict(e.rec)
        # first step of this key. The run's first capture: the real update eagerly on the side stream
        # (it warms up the side stream's cuBLAS handle and workspace and autograd there), then the
        # recording (which runs nothing). Later captures record first and replay for the update:
        # the eager pass cost ~13 ms more than a replay in each of a 5-s run's ~9 captures (H200,
        # scripts/budget_timeline.py, docs/perf-notes/2026-11-30-capture-without-eager-pass.md).
        t0 = time.perf_counter()
        cur = torch.cuda.current_stream(self.device)
        self.side.wait_stream(cur)
        warm = self.captured == 0

        def update():  # the padded step on the entry's buffers: run eagerly, or recorded under capture
            e.mark_live()
            return tr.compute(e.batch, e.xr, e.smp, p, valid=e.valid, device_adam=True, fits=e.fits)

        rec = None
        if warm:
            with torch.cuda.stream(self.side):
                rec = update()
            cur.wait_stream(self.side)
        try:
            g = torch.cuda.CUDAGraph()
            tr.opt.zero_grad(set_to_none=True)  # the graph allocates its own gradients
            with torch.cuda.graph(g, stream=self.side):
                out = update()
            cur.wait_stream(self.side)
            e.graph, e.rec = g, out
            self.captured += 1
            if not warm:  # the step's update: the graph just recorded
                g.replay()
                rec = dict(out)
            self.captures.append({"step": tr.step, "rays": key[0], "capacity": e.capacity,
                                  "seconds": round(time.perf_counter() - t0, 4)})
        except Exception as err:  # noqa: BLE001 - any capture failure falls back to eager steps
            self.enabled = False
            self.cache.clear()
            if self.console is not None:
                self.console.print(f"CUDA graph capture failed ({type(err).__name__}: {str(err).splitlines()[0][:120]}); "
                                   "training goes on with eager steps (run.cuda_graph=off hides this)")
            if rec is None:  # nothing ran yet: this step's update, eagerly
                cur.wait_stream(self.side)
                rec = update()
        return rec

    def capped(self, tr, batch: dict, xr: torch.Tensor, p: float) -> tuple | None:
        """This step's (key, entry) when it can replay a captured graph without the march's host
        sync: its sample count estimated from the last one read back (scaled to this ray count,
        :data:`CAP_MARGIN` above) picks a key whose graph exists. None: the step counts its
        samples on the host (:meth:`step`), as the first steps of a key and a count that
        outgrew its capacities do. A step whose samples then do not fit is not applied (the
        guard's flag, ``fits``) and the next one plans from its larger count."""
        est = self._estimate(batch["origins"].shape[0])
        if est is None:
            return None
        key, e = self._plan(tr, batch, xr, est, p, create=False)
        return None if e is None or e.graph is None else (key, e)

    def run_capped(self, tr, key: tuple, e: _Entry, p: float) -> dict:
        """Replay ``e``'s graph after the capped march wrote into its buffers (no host sync), and
        start reading its sample count back for the next steps' estimate."""
        tr.fill_step_scalars(p)
        tr.opt.prepare_device_step()
        self.cache.move_to_end(key)
        e.graph.replay()
        self.replayed += 1
        self.unsynced += 1
        self._read_back(e.total, e.smp["offsets"].shape[0])
        return dict(e.rec)

    def samples_estimate(self, rays: int) -> int:
        """The sample count of a step of ``rays`` rays from the last one known (0: none yet)."""
        if self._last is None:
            return 0
        s, r = self._last
        return int(round(s * rays / max(1, r)))

    def _poll(self) -> None:
        if self._lag is not None and self._lag["pending"] and self._lag["event"].query():
            self._last = (int(self._lag["host"][0]), self._lag["rays"])
            self._lag["pending"] = False

    def _estimate(self, rays: int) -> int | None:
        self._poll()
        if self._last is None:
            return None
        return int(math.ceil(self.samples_estimate(rays) * CAP_MARGIN))

    def _read_back(self, total: torch.Tensor, rays: int) -> None:
        """An asynchronous copy of ``total`` to page-locked memory (one in flight at a time: a
        step whose copy would overwrite one not yet done skips it)."""
        self._poll()
        if self._lag is None:
            self._lag = {"host": torch.zeros(1, dtype=torch.int32, pin_memory=True), "event": torch.cuda.Event(),
                         "pending": False, "rays": 0}
        if self._lag["pending"]:
            return
        self._lag["host"].copy_(total, non_blocking=True)
        self._lag["event"].record(torch.cuda.current_stream(self.device))  # the copy's stream (cuda:N too)
        self._lag["pending"], self._lag["rays"] = True, rays

    def _make_room(self) -> None:
        """Before a new graph: drop the least recently used ones while less than
        ``MIN_FREE`` of the GPU's memory is free. Each graph keeps a private pool of its step's
        activations (~9 GB at 2^18 samples), so eight of them filled an 80-GB H100 and the
        next eager step ran out of memory; a dropped graph is captured again when its key
        returns. A host query only, made when a key is new."""
        while self.cache:
            free, total = torch.cuda.mem_get_info(self.device)
            if free >= MIN_FREE * total:
                return
            self.cache.popitem(last=False)
            self.evicted += 1
            torch.cuda.empty_cache()

    def release(self) -> None:
        """Drop every captured graph and give its memory pool back (the end of training: the
        export runs eagerly, and a later fit captures again). Without it the pools (~9 GB per
        graph at 2^18 samples) outlived the run until Python's cycle collector freed the trainer,
        so a second scene trained in the same process (the Python API in a loop, quality.py)
        found the GPU full: the H100 ran out of memory in the third 10-s run."""
        self._inputs, self._drawn = {}, {}
        if not self.cache:
            return
        self.cache.clear()
        torch.cuda.synchronize(self.device)
        torch.cuda.empty_cache()

    def summary(self) -> dict:
        return {"graphs": len(self.cache), "captured": self.captured, "replayed": self.replayed, "eager": self.eager,
                "eager_reasons": dict(self.eager_reasons), "evicted": self.evicted, "unsynced": self.unsynced,
                "drawn": self.drawn_steps, "captures": self.captures[:64]}
