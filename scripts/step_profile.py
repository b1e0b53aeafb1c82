"""Where a training step's wall time goes on the GPU: kernels vs launches vs host syncs.

    python scripts/step_profile.py SCENE [--device cuda] [--warm-steps 200] [--steps 20]
                                   [--out DIR] [--sync-sites N] [--timeline K] [--gemm-ops K] [key=value ...]

Builds the device's default trainer (fewview on CUDA, cpu-quick on CPU, plus the overrides),
trains ``--warm-steps`` steps untimed (so the occupancy grid and the sample counts are those of
a run under way), then runs ``--steps`` unmodified ``Trainer.train_step`` calls under
``torch.profiler`` (CPU and CUDA activity; CUPTI sees Warp's kernels as well as torch's).
Per step it reports the wall time, the number of GPU kernels and memory copies launched,
the GPU busy time (the union of the kernel and copy intervals on the device), the share of
the wall time the GPU is idle, the host syncs inside the step (``cudaStreamSynchronize`` /
``cudaDeviceSynchronize`` / ``cudaEventSynchronize``, which blocking device-to-host copies call;
not the synchronize that ends each measured step) and the kernels that take the most
device time. A step whose GPU is idle most of the wall time is launch- (host-) bound: faster
kernels cannot help it, fewer launches (CUDA graphs, fused ops) can.

``--timeline K`` (CUDA) profiles K steps back to back, with no synchronize between them (the
steady state, where a step's host work overlaps the previous step's GPU work), and reports the
device's span, its busy time and its idle gaps, summed per pair of neighbouring operations: an idle
that follows the march's count read is the host's work between that sync and the next launch.

``--gemm-ops K`` (CUDA) profiles K eager steps with input shapes and lists which torch op, at which
shapes, launched each matrix-product kernel (perf note 33: the ``align1`` kernel is every weight
gradient).

Writes ``OUT/step-profile.json`` and ``OUT/step-profile.md``; prints the Markdown.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import (command_line, default_preset, make_trainer, md_table, median, provenance_line,  # noqa: E402
                       ratio, write_results)

# runtime calls (torch) and their driver twins (Warp calls the driver), where CUPTI reports them
SYNC_NAMES = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize",
              "cuStreamSynchronize", "cuCtxSynchronize", "cuEventSynchronize")
STEP_RANGE = "fastneus.train_step"


def sync_site(stack, filename: str, lineno: int) -> str:
    """A sync warning's site: its innermost frame in fastneus' own code (``fastneus/`` or
    ``kernels/``), else the file and line the warning names (torch's internals, e.g. a sync
    inside the autograd engine's backward).

    Args:
        stack: ``traceback.extract_stack()`` at the warning; filename, lineno: the warning's.
    """
    own = [f for f in stack if "fastneus" in Path(f.filename).parts or "kernels" in Path(f.filename).parts]
    if own:
        f = own[-1]
        return f"{Path(f.filename).name}:{f.lineno} in {f.name}"
    return f"{Path(filename).name}:{lineno} (outside fastneus)"


def sync_sites(tr, steps: int) -> list[dict]:
    """Where the host waits for the device in ``steps`` training steps: torch's sync debug mode
    warns at every synchronising torch call (:func:`sync_site` names it). Warp's own waits (a
    ``wp.synchronize``, an array read on the host) are not torch calls and are not seen here;
    the profiler's count (:data:`SYNC_NAMES`) includes them where CUPTI reports driver calls.

    Returns:
        [{"site": "path:line in function", "per_step": float}] most frequent first.
    """
    import traceback
    import warnings

    counts: dict[str, int] = {}

    def note(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" not in str(message):
            return
        key = sync_site(traceback.extract_stack(), filename, lineno)
        counts[key] = counts.get(key, 0) + 1

    with warnings.catch_warnings():  # restores showwarning and the filters on the way out
        warnings.simplefilter("always")
        warnings.showwarning = note
        torch.cuda.set_sync_debug_mode("warn")
        try:
            for _ in range(steps):
                tr.train_step()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return [{"site": k, "per_step": v / steps} for k, v in sorted(counts.items(), key=lambda kv: -kv[1])]


def _union_ms(intervals: list[tuple[float, float]]) -> float:
    """Total length (ms) of the union of [start, end) intervals given in microseconds."""
    tot, cur_s, cur_e = 0.0, None, None
    for s, e in sorted(intervals):
        if cur_e is None or s > cur_e:
            if cur_e is not None:
                tot += cur_e - cur_s
            cur_s, cur_e = s, e
        else:
            cur_e = max(cur_e, e)
    if cur_e is not None:
        tot += cur_e - cur_s
    return tot / 1000.0


def device_gaps(ops: list[tuple[float, float, str]], min_gap_us: float = 0.0, top_n: int = 12) -> dict:
    """Idle time of a device between its operations, summed per (previous op, next op) pair.

    Args:
        ops: [(start_us, end_us, name)] device operations (kernels, copies), any order; overlapping
            ones (several streams) count as busy together.
        min_gap_us: gaps at most this long are summed into ``small_gaps_ms`` but not listed.
        top_n: how many (previous, next) pairs to list.
    Returns:
        {"span_ms", "busy_ms", "idle_ms", "small_gaps_ms", "n_gaps",
         "gaps": [{"after", "before", "count", "ms"}] largest first}.
    """
    ops = sorted(ops)
    if not ops:
        return {"span_ms": 0.0, "busy_ms": 0.0, "idle_ms": 0.0, "small_gaps_ms": 0.0, "n_gaps": 0, "gaps": []}
    pairs: dict[tuple[str, str], list[float]] = {}
    small, n_gaps, last_end, last_name = 0.0, 0, ops[0][1], ops[0][2]
    for s, e, name in ops[1:]:
        if s > last_end:
            gap = s - last_end
            n_gaps += 1
            if gap <= min_gap_us:
                small += gap
            else:
                acc = pairs.setdefault((last_name[:60], name[:60]), [0, 0.0])
                acc[0] += 1
                acc[1] += gap
        if e >= last_end:
            last_end, last_name = e, name
    span = (last_end - ops[0][0]) / 1000.0
    busy = _union_ms([(s, e) for s, e, _ in ops])
    top = sorted(pairs.items(), key=lambda kv: -kv[1][1])[:top_n]
    return {"span_ms": span, "busy_ms": busy, "idle_ms": span - busy, "small_gaps_ms": small / 1000.0,
            "n_gaps": n_gaps, "gaps": [{"after": a, "before": b, "count": c, "ms": ms / 1000.0}
                                       for (a, b), (c, ms) in top]}


def gaps_by_scope(events: list[dict], min_gap_us: float = 5.0, top_n: int = 12) -> list[dict]:
    """The device's idle gaps (over ``min_gap_us``) by the host part that launched the op ending
    each gap, from a Chrome trace's events (torch's profiler: device ops of category ``kernel``,
    ``gpu_memcpy``, ``gpu_memset``, linked by ``args.correlation`` to their launch calls
    (``cuda_runtime`` / ``cuda_driver``), which lie inside ``user_annotation`` ranges on the
    launching thread (:func:`_scoped`'s names; innermost wins).

    Returns:
        [{"scope", "count", "ms", "late_ms"}] by total gap, largest first; ``late_ms`` is the part
        of those gaps after which the op was still not launched (the device waited for the host).
    """
    dev = sorted((e for e in events if e.get("cat") in ("kernel", "gpu_memcpy", "gpu_memset") and "dur" in e),
                 key=lambda e: e["ts"])
    launch = {e["args"]["correlation"]: e for e in events
              if e.get("cat") in ("cuda_runtime", "cuda_driver") and "correlation" in e.get("args", {})}
    ann = [e for e in events if e.get("cat") == "user_annotation" and "dur" in e]
    out: dict[str, list[float]] = {}
    last_end = None
    for e in dev:
        if last_end is not None and e["ts"] - last_end > min_gap_us:
            gap = e["ts"] - last_end
            lc = launch.get(e.get("args", {}).get("correlation"))
            scope, late = "(launch not found)", 0.0
            if lc is not None:
                inside = [a for a in ann if a.get("tid") == lc.get("tid") and a["ts"] <= lc["ts"] <= a["ts"] + a["dur"]]
                scope = min(inside, key=lambda a: a["dur"])["name"] if inside else "(no scope)"
                late = min(gap, max(0.0, lc["ts"] + lc.get("dur", 0.0) - last_end))
            acc = out.setdefault(scope, [0, 0.0, 0.0])
            acc[0] += 1
            acc[1] += gap
            acc[2] += late
        end = e["ts"] + e["dur"]
        last_end = end if last_end is None else max(last_end, end)
    rows = sorted(out.items(), key=lambda kv: -kv[1][1])[:top_n]
    return [{"scope": k, "count": c, "ms": ms / 1000.0, "late_ms": late / 1000.0} for k, (c, ms, late) in rows]


def _scoped(tr) -> list:
    """Name the host parts of a training step in the profile (``record_function`` around the
    trainer's schedule, ray draw, march, graph step, input copies and Adam's host half), for a
    trace that says which part the device waits on. Returns the undo list for :func:`_unscope`."""
    from torch.profiler import record_function

    from fastneus.train import trainer as trainer_mod

    def wrap(obj, name):
        fn = getattr(obj, name)
        own = isinstance(obj, type) or not hasattr(obj, "__dict__") or name in vars(obj)

        def scoped(*a, **k):
            with record_function(f"fastneus.{name}"):
                return fn(*a, **k)
        setattr(obj, name, scoped)
        return obj, name, fn if own else None

    undo = [wrap(trainer_mod, "march_samples")]
    for obj, names in ((tr, ("update_grid", "_set_lr", "fill_step_scalars", "compute")), (tr.bank, ("sample",)),
                       (tr.rig, ("rays",)), (tr.field, ("set_progress",)), (tr.opt, ("prepare_device_step",))):
        undo += [wrap(obj, n) for n in names]
    if tr.graphs is not None:
        undo.append(wrap(tr.graphs, "step"))
        from fastneus.train import graphstep
        undo += [wrap(graphstep._Entry, "load")]
    return undo


def _unscope(undo: list) -> None:
    for obj, name, fn in reversed(undo):
        if fn is None:  # a bound method: drop the instance's wrapper
            delattr(obj, name)
        else:
            setattr(obj, name, fn)


def timeline(tr, steps: int, top_n: int = 12, trace: str | None = None) -> dict:
    """``steps`` training steps back to back under the profiler (no synchronize between them);
    the device's gaps (:func:`device_gaps`, gaps over 5 us listed), per step. ``trace``: also
    write the profile as a Chrome trace there (host ops, launches and device ops with the links
    between them: which host call each gap waits for)."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()
    samples = 0.0
    undo = _scoped(tr) if trace else []
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        t = time.perf_counter()
        for _ in range(steps):
            st = tr.train_step()
            samples += float(st.get("samples", 0)) if isinstance(st, dict) else 0.0
        torch.cuda.synchronize()
        wall = (time.perf_counter() - t) * 1000
    _unscope(undo)
    if trace:
        Path(trace).parent.mkdir(parents=True, exist_ok=True)
        prof.export_chrome_trace(trace)
        import json

        by_scope = gaps_by_scope(json.loads(Path(trace).read_text())["traceEvents"], 5.0, top_n)
    # the named host parts (trace) also show on the device as ranges spanning their kernels: not ops
    ops = [(e.time_range.start, e.time_range.end, e.name) for e in prof.events()
           if getattr(e, "device_type", None) is not None and e.device_type.name == "CUDA"
           and not e.name.startswith("fastneus.")]
    g = device_gaps(ops, min_gap_us=5.0, top_n=top_n)
    per = {k: g[k] / steps for k in ("span_ms", "busy_ms", "idle_ms", "small_gaps_ms")}
    return {"steps": steps, "wall_ms": wall / steps, "samples": samples / steps, **per,
            "gaps_per_step": g["n_gaps"] / steps,
            "gaps": [{**r, "count": r["count"] / steps, "ms": r["ms"] / steps} for r in g["gaps"]],
            **({"gaps_by_scope": [{**r, "count": r["count"] / steps, "ms": r["ms"] / steps,
                                   "late_ms": r["late_ms"] / steps} for r in by_scope]} if trace else {})}


def profile_steps(tr, steps: int, top_n: int = 12) -> dict:
    """Profile ``steps`` training steps one by one; medians over the steps."""
    from torch.profiler import ProfilerActivity, profile, record_function

    dev = torch.device(tr.device)
    cuda = dev.type == "cuda"
    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if cuda else [])
    per: dict[str, list[float]] = {k: [] for k in ("wall_ms", "kernels", "copies", "gpu_busy_ms", "syncs",
                                                   "samples")}
    kernel_ms: dict[str, float] = {}
    kernel_n: dict[str, int] = {}  # launches per name: many tiny ones are a fusion candidate, not a slow kernel
    for _ in range(steps):
        if cuda:
            torch.cuda.synchronize()
        with profile(activities=acts) as prof:
            t = time.perf_counter()
            with record_function(STEP_RANGE):
                st = tr.train_step()
            if cuda:
                torch.cuda.synchronize()
            wall = (time.perf_counter() - t) * 1000
        evs = prof.events()
        # the step's own syncs: inside its range (the synchronize that ends the measurement is not the step's)
        rng = [e.time_range for e in evs if e.name == STEP_RANGE and getattr(e, "device_type", None) is not None
               and e.device_type.name == "CPU"]
        lo, hi = (rng[0].start, rng[0].end) if rng else (float("-inf"), float("inf"))
        dev_iv, n_k, n_c, n_sync = [], 0, 0, 0
        for e in evs:
            dt = getattr(e, "device_type", None)
            on_dev = dt is not None and dt.name == "CUDA" and e.name != STEP_RANGE  # the range's GPU twin spans the step
            if on_dev:
                iv = e.time_range
                dev_iv.append((iv.start, iv.end))
                name = e.name
                if "memcpy" in name.lower() or "memset" in name.lower():
                    n_c += 1
                else:
                    n_k += 1
                    kernel_ms[name] = kernel_ms.get(name, 0.0) + (iv.end - iv.start) / 1000.0
                    kernel_n[name] = kernel_n.get(name, 0) + 1
            elif e.name in SYNC_NAMES and lo <= e.time_range.start <= hi:
                n_sync += 1
        per["wall_ms"].append(wall)
        per["kernels"].append(n_k)
        per["copies"].append(n_c)
        per["gpu_busy_ms"].append(_union_ms(dev_iv))
        per["syncs"].append(n_sync)
        per["samples"].append(float(st.get("samples", 0)) if isinstance(st, dict) else 0.0)
    med = {k: median(v) for k, v in per.items()}
    med["gpu_idle_pct"] = 100.0 * max(0.0, 1.0 - ratio(med["gpu_busy_ms"], med["wall_ms"]))
    med["samples_per_s_M"] = ratio(med["samples"], med["wall_ms"]) / 1000.0
    top = sorted(kernel_ms.items(), key=lambda kv: -kv[1])[:top_n]
    total_k = sum(kernel_ms.values())
    return {"steps": steps, "median": med,
            "top_kernels": [{"kernel": k[:90], "ms_per_step": v / steps, "share_pct": 100 * ratio(v, total_k),
                             "launches_per_step": kernel_n[k] / steps} for k, v in top]}


def is_gemm_kernel(name: str) -> bool:
    """Whether a CUDA kernel name is a cuBLAS / CUTLASS matrix product (or GEMV)."""
    n = name.lower()
    return any(k in n for k in ("gemm", "gemv", "cutlass"))


def gemm_ops(tr, steps: int) -> list[dict]:
    """Which torch op, at which input shapes, launched each matrix-product kernel: ``steps``
    eager steps (no captured graph: a replay hides the ops) profiled with shapes; per (op,
    shapes, kernel) the device ms per step, largest first. ``align1`` in a kernel's name means
    cuBLAS could not load four floats at a time from one operand (a row length not a multiple
    of 4), the cue for padding that product.
    """
    from torch.profiler import ProfilerActivity, profile

    graphs, tr.graphs = tr.graphs, None  # eager: every product is its own op
    try:
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], record_shapes=True) as prof:
            for _ in range(steps):
                tr.train_step()
            torch.cuda.synchronize()
    finally:
        tr.graphs = graphs
    acc: dict[tuple, float] = {}
    for e in prof.events():
        for k in getattr(e, "kernels", []) or []:
            if is_gemm_kernel(k.name):
                key = (e.name, str(e.input_shapes), k.name[:110])
                acc[key] = acc.get(key, 0.0) + k.duration / 1000.0
    rows = [{"op": op, "shapes": shapes, "kernel": kern, "ms_per_step": ms / steps}
            for (op, shapes, kern), ms in acc.items()]
    return sorted(rows, key=lambda r: -r["ms_per_step"])


def unprofiled_step_ms(tr, steps: int) -> float:
    """Mean wall ms per step over ``steps`` steps, synchronised only at both ends."""
    sync = torch.cuda.synchronize if str(tr.device).startswith("cuda") else (lambda: None)
    sync()
    t0 = time.perf_counter()
    for _ in range(steps):
        tr.train_step()
    sync()
    return 1000.0 * (time.perf_counter() - t0) / steps


def host_profile(tr, steps: int, top: int) -> dict:
    """cProfile of ``steps`` steps as a run takes them (no sync but the loop's own): where the
    host's time per step goes when the device waits for it. Functions by their own time."""
    import cProfile
    import pstats

    sync = torch.cuda.synchronize if str(tr.device).startswith("cuda") else (lambda: None)
    sync()
    pr = cProfile.Profile()
    t0 = time.perf_counter()
    pr.enable()
    for _ in range(steps):
        tr.train_step()
    pr.disable()
    sync()
    wall = 1000.0 * (time.perf_counter() - t0) / steps
    st = pstats.Stats(pr)
    rows = []
    for (file, line, name), (cc, nc, tt, ct, _) in st.stats.items():
        rows.append({"function": f"{Path(file).name}:{line}({name})", "calls_per_step": nc / steps,
                     "own_ms_per_step": 1000.0 * tt / steps, "cum_ms_per_step": 1000.0 * ct / steps})
    own = sorted(rows, key=lambda r: -r["own_ms_per_step"])[:top]
    cum = sorted(rows, key=lambda r: -r["cum_ms_per_step"])[:top]
    return {"steps": steps, "wall_ms_per_step_profiled": wall, "by_own_time": own, "by_cumulative_time": cum}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--warm-steps", type=int, default=200)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--out", default="step-profile")
    ap.add_argument("--top", type=int, default=12, help="how many kernels to list")
    ap.add_argument("--sync-sites", type=int, default=0, metavar="N",
                    help="CUDA: also run N steps under torch's sync debug mode and list where the host waits")
    ap.add_argument("--timeline", type=int, default=0, metavar="K",
                    help="CUDA: also profile K steps back to back and list the device's idle gaps")
    ap.add_argument("--trace", default=None, metavar="FILE",
                    help="with --timeline: write those steps' profile as a Chrome trace (chrome://tracing, Perfetto)")
    ap.add_argument("--gemm-ops", type=int, default=0, metavar="K",
                    help="CUDA: also profile K eager steps with shapes and list which op launched each matrix-product "
                         "kernel (align1 = an operand's rows not a multiple of 4 floats)")
    ap.add_argument("--host-profile", type=int, default=0, metavar="K",
                    help="also run K steps under cProfile and list the host functions taking the most time")
    ap.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = ap.parse_intermixed_args()  # key=value overrides may follow the options

    from fastneus.formats.detect import load_scene
    from fastneus.kernels import prepare_kernels

    out = Path(args.out)
    scene = load_scene(Path(args.scene))
    preset = default_preset(args.device)
    prepare_kernels(args.device, say=print)
    tr = make_trainer(scene, args.device, args.overrides, out / "run", preset)
    for _ in range(args.warm_steps):
        tr.train_step()
    res = profile_steps(tr, args.steps, args.top)
    m = res["median"]
    # the same steps outside the profiler (its per-launch bookkeeping inflates a host-bound wall)
    m["unprofiled_ms"] = unprofiled_step_ms(tr, max(args.steps, 20))
    m["samples_per_s_M_unprofiled"] = ratio(m["samples"], m["unprofiled_ms"]) / 1000.0
    if args.sync_sites > 0 and args.device.startswith("cuda"):
        res["sync_sites"] = sync_sites(tr, args.sync_sites)
    if args.timeline > 0 and args.device.startswith("cuda"):
        res["timeline"] = timeline(tr, args.timeline, args.top, args.trace)
    if args.gemm_ops > 0 and args.device.startswith("cuda"):
        res["gemm_ops"] = gemm_ops(tr, args.gemm_ops)
    if args.host_profile > 0:
        res["host_profile"] = host_profile(tr, args.host_profile, max(args.top, 25))
    cmd = command_line("step_profile.py")
    head = (f"{provenance_line(args.device, cmd)} Medians per step ({preset} preset, {tr.n_rays} rays per step)."
            "\n\n")
    row = {k: round(v, 2) for k, v in m.items()}
    md = head + md_table([row], ["wall_ms", "gpu_busy_ms", "gpu_idle_pct", "kernels", "copies", "syncs", "samples",
                                 "samples_per_s_M", "unprofiled_ms", "samples_per_s_M_unprofiled"])
    md += "\n\nKernels taking the most device time (ms per step, share of all kernel time):\n\n"
    md += md_table([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}
                    for r in res["top_kernels"]], ["kernel", "ms_per_step", "share_pct", "launches_per_step"])
    if res.get("sync_sites"):
        md += "\n\nWhere the host waits for the device (torch's sync debug mode, per step):\n\n"
        md += md_table(res["sync_sites"], ["site", "per_step"])
    if res.get("timeline"):
        tl = res["timeline"]
        md += (f"\n\n{tl['steps']} steps back to back (no sync between), per step: wall {tl['wall_ms']:.2f} ms, "
               f"device span {tl['span_ms']:.2f}, busy {tl['busy_ms']:.2f}, idle {tl['idle_ms']:.2f} "
               f"({tl['gaps_per_step']:.0f} gaps, {tl['small_gaps_ms']:.2f} ms in gaps <= 5 us), "
               f"{tl['samples']:.0f} samples. The largest idle gaps, by the operations either side:\n\n")
        md += md_table([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()} for r in tl["gaps"]],
                       ["after", "before", "count", "ms"])
        if tl.get("gaps_by_scope"):
            md += ("\n\nThe same gaps by the host part that launched the op ending each (late_ms: the op was "
                   "launched only after the device had gone idle):\n\n")
            md += md_table([{k: (round(v, 3) if isinstance(v, float) else v) for k, v in r.items()}
                            for r in tl["gaps_by_scope"]], ["scope", "count", "ms", "late_ms"])
    if res.get("host_profile"):
        hp = res["host_profile"]
        md += (f"\n\nThe host under cProfile, {hp['steps']} steps ({hp['wall_ms_per_step_profiled']:.2f} ms per step "
               "profiled); functions by their own time per step:\n\n")
        md += md_table([{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
                        for r in hp["by_own_time"]], ["function", "calls_per_step", "own_ms_per_step", "cum_ms_per_step"])
        md += "\n\nBy cumulative time per step:\n\n"
        md += md_table([{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
                        for r in hp["by_cumulative_time"]],
                       ["function", "calls_per_step", "own_ms_per_step", "cum_ms_per_step"])
    if res.get("gemm_ops"):
        md += ("\n\nMatrix-product kernels by the op and input shapes that launched them (eager steps, ms per "
               "step):\n\n")
        md += md_table([{k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
                        for r in res["gemm_ops"][:30]], ["op", "shapes", "kernel", "ms_per_step"])
    write_results(out, "step-profile", {"args": vars(args), "preset": preset, "rays": tr.n_rays, **res}, md,
                  args.device, cmd)
    print(md)


if __name__ == "__main__":
    main()
