"""What one split CPU launch costs: the thread pool's hand-off against torch's own threads.

    python scripts/split_overhead.py [--threads 2] [--sizes 512,2048,8192,32768,131072]
                                     [--repeat 50] [--out DIR]

On the CPU every Warp kernel of fastneus runs as a serial loop; ``kernels/_warp.py`` cuts a
launch into chunks and runs them on a Python thread pool (``run_tasks``). Each split launch pays
for waking the pool's threads and handing the GIL between them. This script measures, on this
machine and in this process:

- the pool's round trip: ``run_tasks`` over ``threads`` no-op tasks (nothing but the hand-off);
- the hash-grid forward (``hash_encode``, 8 levels, a 2^15 table: the cpu-quick preset's grid)
  at several point counts, on one thread and split over ``--threads``: the speed-up of a real
  kernel, and the point count from which splitting pays;
- for comparison, torch's ``exp`` on as many floats as the hash forward writes, on one thread
  and on ``--threads`` OpenMP threads (native threads that spin between parallel regions).

Medians of ``--repeat`` calls. Writes ``OUT/split-overhead.json`` / ``.md`` with the machine, the
command and the commit; prints the Markdown. No number here is asserted anywhere.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import fastneus  # noqa: F401 - before torch: it sets torch's OpenMP spin (GOMP_SPINCOUNT), read when torch loads
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchutil import command_line, md_table, parse_counts, provenance_line, time_fn, write_results  # noqa: E402


def measure(threads: int, sizes: list[int], repeat: int) -> dict:
    """The round trip and the per-size rows (milliseconds, medians over ``repeat`` calls)."""
    from fastneus.kernels import configure_threads, get_op, run_on_threads
    from fastneus.kernels.hashgrid import HashGridConfig

    hash_encode = get_op("hash_encode")
    saved = torch.get_num_threads()
    noop = [lambda: None] * threads
    configure_threads(threads, torch_threads=False)
    run_on_threads(noop)  # the pool's threads exist before the clock
    round_trip = time_fn(lambda: run_on_threads(noop), "cpu", warmup=5, repeat=repeat * 4)
    cfg = HashGridConfig(levels=8, log2_table=15, finest_res=256)
    table = torch.randn(cfg.levels, cfg.table_size, cfg.features, generator=torch.Generator().manual_seed(0)) * 1e-2
    rows = []
    for n in sizes:
        u = torch.rand(n, 3, generator=torch.Generator().manual_seed(n))
        row = {"points": n}
        for t, name in ((1, "hash 1 thread ms"), (threads, f"hash {threads} threads ms")):
            configure_threads(t, torch_threads=False)
            hash_encode(u, table, cfg)  # the first launch of a kernel is serial (its module loads)
            row[name] = time_fn(lambda: hash_encode(u, table, cfg), "cpu", repeat=repeat)
        row["hash speed-up"] = row["hash 1 thread ms"] / max(row[f"hash {threads} threads ms"], 1e-9)
        x = torch.rand(n * cfg.levels * cfg.features)
        for t, name in ((1, "exp 1 thread ms"), (threads, f"exp {threads} threads ms")):
            torch.set_num_threads(t)
            row[name] = time_fn(lambda: torch.exp(x), "cpu", repeat=repeat)
        row["exp speed-up"] = row["exp 1 thread ms"] / max(row[f"exp {threads} threads ms"], 1e-9)
        rows.append(row)
    configure_threads(saved)
    return {"threads": threads, "pool_round_trip_ms": round_trip, "rows": rows}


def report(res: dict, command: str) -> str:
    t = res["threads"]
    cols = ["points", "hash 1 thread ms", f"hash {t} threads ms", "hash speed-up", "exp 1 thread ms",
            f"exp {t} threads ms", "exp speed-up"]
    return "\n".join([
        "# What one split CPU launch costs", "", provenance_line("cpu", command), "",
        f"Thread pool round trip ({t} no-op tasks through `run_tasks`): **{res['pool_round_trip_ms']:.3f} ms**.",
        "", md_table(res["rows"], cols), ""])


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", default="512,2048,8192,32768,131072")
    ap.add_argument("--repeat", type=int, default=50)
    ap.add_argument("--out", default="/tmp/fastneus-split-overhead")
    args = ap.parse_args(argv)
    if args.threads < 2:
        raise SystemExit(f"--threads: a split needs at least 2 threads, got {args.threads}")
    if args.repeat < 1:
        raise SystemExit(f"--repeat: expected a positive count, got {args.repeat}")
    sizes = parse_counts(args.sizes, "--sizes")
    res = measure(args.threads, sizes, args.repeat)
    command = command_line("split_overhead.py", argv)
    text = report(res, command)
    write_results(Path(args.out), "split-overhead", res, text, "cpu", command)
    print(text)
    return res


if __name__ == "__main__":
    main()
