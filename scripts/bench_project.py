"""Time project_pattern and laser_light (Warp), forward + backward, optionally A/B against
another version of kernels/project.py (interleaved runs, medians).

    python scripts/bench_project.py --device cpu|cuda [--baseline OLD/project.py] [--repeat N] [--pattern random]

Cases: plain pattern (1x1), learned 5x5 blur, flat port + attenuation (water), both, and
laser planes; S samples over R rays of F frames and P projectors (1024 x 768 patterns).
``--baseline`` loads the given file as a sibling module of ``fastneus.kernels.project`` (its
relative imports resolve there) and times it in alternation with the current one.
"""
from __future__ import annotations

import argparse
import importlib.util
import time

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import median, ratio, sync


def make_inputs(S: int, R: int, F: int, P: int, device: str, gen: torch.Generator, pattern: str = "lines"):
    """Samples packed by ray, in front of projectors that look at the origin from ~2 m."""
    from fastneus.kernels.render import PatternStore

    counts = torch.full((R,), S // R, dtype=torch.int32)
    counts[: S - int(counts.sum())] += 1
    offsets = torch.cumsum(counts, 0, dtype=torch.int32) - counts
    ray_index = torch.repeat_interleave(torch.arange(R, dtype=torch.int32), counts.long())
    K = torch.tensor([[800.0, 0, 512], [0, 800.0, 384], [0, 0, 1]]).expand(F, P, 3, 3).contiguous()
    W = torch.zeros(F, P, 3, 4)
    W[..., :3, :3] = torch.eye(3)
    W[..., 0, 3] = torch.linspace(-0.3, 0.3, P)
    W[..., 2, 3] = 2.0
    if pattern == "lines":  # vertical lines every 16 px, like a laser/line pattern (dark elsewhere)
        pat = torch.zeros(768, 1024, 3, dtype=torch.uint8)
        pat[:, ::16] = 255
        pat[:, 1::16] = 128
    else:  # every texel lit: no zero gradient anywhere
        pat = torch.randint(1, 256, (768, 1024, 3), generator=gen, dtype=torch.uint8)
    pats = [pat.numpy() for _ in range(P)]
    ray_frame = torch.randint(0, F, (R,), generator=gen, dtype=torch.int32)
    pos = torch.rand(S, 3, generator=gen) * 1.2 - 0.6
    inp = dict(pos=pos, ray_index=ray_index, offsets=offsets, counts=counts, ray_frame=ray_frame, proj_K=K,
               proj_W=W, proj_pattern=torch.arange(P, dtype=torch.int32).expand(F, P).contiguous())
    inp = {k: v.to(device).contiguous() for k, v in inp.items()}
    inp["patterns"] = PatternStore(pats, device)
    return inp


def load_baseline(path: str):
    spec = importlib.util.spec_from_file_location("fastneus.kernels._project_baseline", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def cases(mod, inp, P, device):
    """name -> closure running forward + backward of ``mod``'s op on ``inp``; returns (forward + backward
    ms, backward ms)."""
    from fastneus.kernels.project import pack_planes, port_row

    gen = torch.Generator().manual_seed(1)
    up = torch.randn(inp["pos"].shape, generator=gen).to(device)
    port = torch.tensor([port_row([0.0, 0.0, 1.0], 0.03, 0.01)] * P, device=device)
    sigma = torch.tensor([0.3, 0.1, 0.05], device=device)

    def blur(n):
        b = torch.rand(P, n * n, generator=gen) + 0.1
        return (b / b.sum(1, keepdim=True)).to(device)

    class Plane:
        def __init__(self, normal, colour):
            self.normal, self.offset, self.colour = normal, 0.0, colour
            self.width, self.fan_deg, self.axis = 0.01, 60.0, (0.0, 0.0, 1.0)

    planes = pack_planes([[Plane((1.0, 0.0, -0.1), (1, 0, 0)), Plane((0.0, 1.0, 0.05), (0, 1, 0))]] * P, device)
    on = torch.ones(inp["proj_W"].shape[:2], dtype=torch.int32, device=device)

    def timed_grad(loss, ins):
        sync(device)
        t = time.perf_counter()
        torch.autograd.grad(loss, ins)
        sync(device)
        return (time.perf_counter() - t) * 1000

    def run_proj(b, pt, sg):
        def fn():
            pos = inp["pos"].clone().requires_grad_(True)
            W = inp["proj_W"].clone().requires_grad_(True)
            bb = b.clone().requires_grad_(True)
            s = None if sg is None else sg.clone().requires_grad_(True)
            q = mod.project_pattern(pos, inp["ray_index"], inp["offsets"], inp["counts"], inp["ray_frame"],
                                    inp["proj_K"], W, inp["proj_pattern"], inp["patterns"], bb, port=pt, sigma=s)
            ins = [pos, W, bb] + ([s] if s is not None else [])
            return timed_grad((q * up).sum(), ins)
        return fn

    def run_laser():
        pos = inp["pos"].clone().requires_grad_(True)
        W = inp["proj_W"].clone().requires_grad_(True)
        q = mod.laser_light(pos, inp["ray_index"], inp["offsets"], inp["counts"], inp["ray_frame"], W, on, planes)
        return timed_grad((q * up).sum(), [pos, W])

    return {"plain 1x1": run_proj(blur(1), None, None), "blur 5x5": run_proj(blur(5), None, None),
            "water 1x1": run_proj(blur(1), port, sigma), "water+blur 5x5": run_proj(blur(5), port, sigma),
            "laser 2 planes": run_laser}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--baseline", help="another kernels/project.py to time in alternation (A = it, B = current)")
    ap.add_argument("--samples", type=int, default=None, help="default 2^14 on CPU, 2^18 on CUDA")
    ap.add_argument("--rays", type=int, default=None, help="default samples / 32")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--projectors", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--pattern", choices=("lines", "random"), default="lines",
                    help="lines: dark but for a line every 16 px; random: every texel lit")
    ap.add_argument("--only", default="", help="comma-separated case names (substring match)")
    args = ap.parse_args()
    import fastneus.kernels.project as cur

    S = args.samples or (2 ** 18 if args.device.startswith("cuda") else 2 ** 14)
    R = args.rays or max(1, S // 32)
    inp = make_inputs(S, R, args.frames, args.projectors, args.device, torch.Generator().manual_seed(0),
                      args.pattern)
    mods = [("current", cur)]
    if args.baseline:
        mods.insert(0, ("baseline", load_baseline(args.baseline)))
    runs = {name: cases(m, inp, args.projectors, args.device) for name, m in mods}
    names = [c for c in runs["current"] if not args.only or any(o in c for o in args.only.split(","))]
    print(f"S={S} R={R} F={args.frames} P={args.projectors} device={args.device} repeat={args.repeat} "
          f"pattern={args.pattern}")
    for c in names:
        ts = {m: [] for m, _ in mods}
        for m, _ in mods:  # warm-up (compiles)
            runs[m][c]()
        for _ in range(args.repeat):
            for m, _ in mods:  # interleaved A/B
                sync(args.device)
                t = time.perf_counter()
                tb = runs[m][c]()
                sync(args.device)
                ts[m].append(((time.perf_counter() - t) * 1000, tb))
        med = {m: [median(x[j] for x in v) for j in (0, 1)] for m, v in ts.items()}
        line = "  ".join(f"{m} {med[m][0]:8.2f} / {med[m][1]:8.2f} ms" for m, _ in mods)
        if args.baseline:
            line += (f"  current/baseline {ratio(med['current'][0], med['baseline'][0]):.2f} / "
                     f"{ratio(med['current'][1], med['baseline'][1]):.2f}")
        print(f"{c:16s} fwd+bwd / bwd  {line}", flush=True)


if __name__ == "__main__":
    main()
