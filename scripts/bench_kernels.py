"""Time every kernel op (Warp) against its torch twin, forward and backward.

    python scripts/bench_kernels.py --device cpu|cuda [--out DIR] [--no-md]

Sizes: GPU 2^18 samples, 16 levels, 2^19 table; CPU 2^15 samples, 2^17 table.
Prints a table, writes JSON to --out and a section of docs/benchmarks/kernels.md.
"""
from __future__ import annotations

import argparse
import math
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

from benchutil import ROOT, command_line, md_table, provenance, provenance_line, ratio, time_fn, update_section, write_json


def make_render_inputs(S: int, R: int, P: int, device: str, gen: torch.Generator):
    """Random but realistic render inputs: S samples over R rays, P projectors, 2 frames."""
    from fastneus.kernels.render import PatternStore

    counts = torch.full((R,), S // R, dtype=torch.int32)
    offsets = torch.cumsum(counts, 0, dtype=torch.int32) - counts
    ray_index = torch.repeat_interleave(torch.arange(R, dtype=torch.int32), counts.long())
    t0 = torch.rand(S, generator=gen) * 2
    t1 = t0 + 0.004
    F = 2
    dirs = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen), dim=-1)
    K = torch.tensor([[800.0, 0, 512], [0, 800.0, 384], [0, 0, 1]]).expand(F, P, 3, 3).contiguous()
    W = torch.zeros(F, P, 3, 4)
    W[..., :3, :3] = torch.eye(3)
    W[..., 0, 3] = torch.linspace(-0.3, 0.3, P)
    W[..., 2, 3] = 3.0
    pats = [(torch.rand(768, 1024, 3, generator=gen) * 255).to(torch.uint8).numpy() for _ in range(P)]
    inp = dict(
        sdf=(torch.randn(S, generator=gen) * 0.05), grad=torch.randn(S, 3, generator=gen),
        color=torch.rand(S, 3, generator=gen), pos=torch.rand(S, 3, generator=gen) * 1.6 - 0.8,
        t0=t0, t1=t1, ray_index=ray_index, offsets=offsets, counts=counts, dirs=dirs,
        ray_frame=torch.randint(0, F, (R,), generator=gen, dtype=torch.int32),
        proj_K=K, proj_W=W, proj_pattern=torch.arange(P, dtype=torch.int32).expand(F, P).contiguous(),
    )
    inp = {k: v.to(device).contiguous() for k, v in inp.items()}
    inp["patterns"] = PatternStore(pats, device)
    return inp


def bench(device: str, quick: bool = False) -> list[dict]:
    from fastneus.kernels import get_op
    from fastneus.kernels.hashgrid import HashGridConfig, init_table
    from fastneus.kernels.occupancy import march_rays, march_rays_torch, occupancy_alpha, occupancy_alpha_torch

    gpu = device.startswith("cuda")
    N = 2 ** 18 if gpu else 2 ** 15
    if quick:
        N = 2 ** 12
    log2T = 19 if gpu else 17
    gen = torch.Generator().manual_seed(0)
    rows = []
    rep = 20 if gpu else 5
    twin_rep = rep if gpu else 2

    # ---- hash encoding
    cfg = HashGridConfig(levels=16, features=2, log2_table=log2T, base_res=16, finest_res=2048)
    u = torch.rand(N, 3, generator=gen).to(device)
    table = init_table(cfg, device).requires_grad_(True)
    up = torch.randn(N, cfg.levels * cfg.features, generator=gen).to(device)
    for backend in ("warp", "torch"):
        enc = get_op("hash_encode", backend)
        r = rep if backend == "warp" else twin_rep
        fwd = time_fn(lambda: enc(u, table.detach(), cfg), device, repeat=r)

        def fb():
            table.grad = None
            enc(u, table, cfg).backward(up)
        both = time_fn(fb, device, repeat=r)
        rows.append({"op": "hash_encode (16 lvl)", "backend": backend, "n": N, "fwd_ms": fwd, "fwd_bwd_ms": both})

    # ---- marching: rays through a sphere-shell occupancy grid, ~N samples in total
    res = 128
    lin = (torch.arange(res) + 0.5) / res * 2 - 1
    X, Y, Z = torch.meshgrid(lin, lin, lin, indexing="ij")
    rad = torch.sqrt(X ** 2 + Y ** 2 + Z ** 2)
    bits = ((rad - 0.5).abs() < 0.05).to(torch.uint8).reshape(-1).to(device)
    step = math.sqrt(3) * 2 / 1024
    R = max(64, N // 64)
    o = torch.tensor([0.0, 0.0, -2.5]).expand(R, 3).contiguous().to(device)
    d = torch.nn.functional.normalize(torch.randn(R, 3, generator=gen) * 0.15 + torch.tensor([0, 0, 1.0]), dim=-1).to(device)
    jit = torch.rand(R, generator=gen).to(device)
    for backend, fn in (("warp", march_rays), ("torch", march_rays_torch)):
        ms = time_fn(lambda: fn(o, d, bits, res, step, 1024, jit, "sphere", 0.0), device,
                     repeat=rep if backend == "warp" else twin_rep)
        S = int(fn(o, d, bits, res, step, 1024, jit, "sphere", 0.0)[2].shape[0])
        rows.append({"op": f"march_rays ({R} rays -> {S} samples)", "backend": backend, "n": R, "fwd_ms": ms})

    # ---- occupancy alpha over the whole grid
    sdf = (torch.randn(res ** 3, generator=gen) * 0.3).to(device)
    for backend, fn in (("warp", occupancy_alpha), ("torch", occupancy_alpha_torch)):
        ms = time_fn(lambda: fn(sdf, 50.0, step), device, repeat=rep)
        rows.append({"op": f"occupancy_alpha ({res}^3)", "backend": backend, "n": res ** 3, "fwd_ms": ms})

    # ---- volume rendering with pattern projection
    R = N // 64
    inp = make_render_inputs(N, R, 4, device, gen)
    diff = ("sdf", "grad", "color", "pos", "proj_W")
    inv_s, i_r, i_b = (torch.tensor([v], device=device) for v in (40.0, 0.4, 0.1))
    for backend in ("warp", "torch"):
        render = get_op("render_pattern", backend)
        r = rep if backend == "warp" else twin_rep
        fwd = time_fn(lambda: render(**inp, inv_s=inv_s, cos_anneal=0.5, i_r=i_r, i_b=i_b), device, repeat=r)
        leaves = {k: inp[k].clone().requires_grad_(True) for k in diff}
        pars = [p.clone().requires_grad_(True) for p in (inv_s, i_r, i_b)]
        ups = [torch.randn(R, 3, device=device), torch.randn(R, device=device), torch.randn(R, device=device),
               torch.randn(R, 3, device=device)]

        def fb():
            out = render(**{**inp, **leaves}, inv_s=pars[0], cos_anneal=0.5, i_r=pars[1], i_b=pars[2])
            loss = sum((out[k] * g).sum() for k, g in zip(("color", "opacity", "depth", "texture"), ups))
            loss.backward()
        both = time_fn(fb, device, repeat=r)
        rows.append({"op": "render_pattern (4 proj)", "backend": backend, "n": N, "fwd_ms": fwd, "fwd_bwd_ms": both})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks"))
    ap.add_argument("--no-md", action="store_true", help="do not touch docs/benchmarks/kernels.md")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (smoke test)")
    args = ap.parse_args()
    torch.set_grad_enabled(True)
    rows = bench(args.device, args.quick)
    # speed-up of warp over its twin, per op
    by = {(r["op"], r["backend"]): r for r in rows}
    for r in rows:
        if r["backend"] == "warp" and (r["op"], "torch") in by:
            t = by[(r["op"], "torch")]
            key = "fwd_bwd_ms" if "fwd_bwd_ms" in r else "fwd_ms"
            r["speedup_vs_twin"] = ratio(t[key], r[key])
    cols = ["op", "backend", "n", "fwd_ms", "fwd_bwd_ms", "speedup_vs_twin"]
    table = md_table(rows, cols)
    print(table)
    kind = "cuda" if args.device.startswith("cuda") else "cpu"
    out = Path(args.out)
    cmd = command_line("bench_kernels.py")
    write_json(out / f"kernels-{kind}.json", {**provenance(args.device, cmd), "rows": rows})
    if not args.no_md and not args.quick:
        text = (f"### Kernels on {kind.upper()}\n\n{provenance_line(args.device, cmd)} Medians after warm-up, "
                f"milliseconds.\n\n{table}")
        update_section(ROOT / "docs" / "benchmarks" / "kernels.md", f"kernels-{kind}", text)


if __name__ == "__main__":
    main()
