"""Long fuzz runs of every input parser (the strategies of tests/fuzz_strategies.py).

Each example mutates a valid small input (scene.json, transforms.json, cameras_sphere.npz,
OpenCV calibration, COLMAP text, config YAML, key=value overrides) and calls the loader
the verbs call. Anything but success or a one-line FastneusError naming an input file is
a bug: it is reported once per distinct cause (exception type and where it was raised),
and the input is saved under ``--save`` (one folder per failure: the mutated files,
``what.txt`` with the mutation and the traceback). A native crash (SIGSEGV, abort) ends the
process: the input that caused it is left in ``--save/last-<target>``.

Usage::

    python scripts/fuzz.py --examples 2000 --target all --save fuzz-failures
    python scripts/fuzz.py --examples 500 --target npz --seed 1 --save /tmp/f

Exit status 1 when a failure was found, else 0.
"""
from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import fuzz_strategies as fz  # noqa: E402  (tests/ on the path above)

ALIASES = {"npz": ("activeneus", "neus"), "all": fz.TARGETS}


def _cause(e: BaseException) -> str:
    """Exception type and the innermost fastneus frame: one key per distinct bug."""
    tb = traceback.extract_tb(e.__traceback__)
    ours = [f for f in tb if "fastneus" in f.filename and "fuzz_strategies" not in f.filename] or tb[-1:]
    where = f"{Path(ours[-1].filename).name}:{ours[-1].lineno}" if ours else "?"
    return f"{type(e).__name__} at {where}"


def _save(folder: Path, n: int, case: fz.Case, cause: str, e: BaseException | None, name: str | None = None) -> Path:
    d = folder / (name or f"{case.target}-{n:04d}")
    d.mkdir(parents=True, exist_ok=True)
    for name, data in case.files.items():
        (d / name).write_bytes(data)
    if case.items:
        (d / "overrides.txt").write_text("\n".join(map(repr, case.items)) + "\n")
    text = f"target: {case.target}\nmutation: {case.what}\ncause: {cause}\n\n" + \
        ("".join(traceback.format_exception(type(e), e, e.__traceback__)) if e else "")
    (d / "what.txt").write_bytes(text.encode("utf-8", "backslashreplace"))  # mutations hold lone surrogates
    return d


def run_target(f: fz.Fuzz, target: str, examples: int, seed: int | None, save: Path, found: dict,
               keep_last: bool = True) -> tuple[int, int]:
    """Run ``examples`` cases of ``target``; returns (examples run, FastneusErrors seen).

    With ``keep_last``, each case is first written to ``save/last-<target>`` so that a crash of
    the process itself leaves its input behind (removed when the target finishes).
    """
    from hypothesis import HealthCheck, given, settings
    from hypothesis import seed as hseed

    counts = [0, 0]
    crash_dir = save / f"last-{target}" if keep_last else None

    @settings(max_examples=examples, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(case=f.strategy(target))
    def one(case):
        counts[0] += 1
        if crash_dir is not None:  # a native crash (SIGSEGV, abort) kills this process: its input stays here
            shutil.rmtree(crash_dir, ignore_errors=True)
            _save(crash_dir.parent, 0, case, "the process died on this input (a native crash)", None,
                  name=crash_dir.name)
        t0 = time.perf_counter()
        try:
            if fz.check_case(f, case) != "ok":
                counts[1] += 1
        except (Exception, fz.Hang) as e:  # noqa: BLE001 - every other outcome is a finding
            cause = _cause(e) if not isinstance(e, AssertionError) else f"property: {str(e)[:90]}"
            if cause not in found:
                found[cause] = _save(save, len(found), case, cause, e)
                print(f"  NEW {target}: {cause}\n      {str(e)[:200]!r}\n      input: {found[cause]}", flush=True)
        dt = time.perf_counter() - t0
        if dt > 2.0:
            print(f"  slow {target} example: {dt:.1f} s ({case.what[:100]})", flush=True)

    if seed is not None:
        one = hseed(seed)(one)
    one()
    if crash_dir is not None:
        shutil.rmtree(crash_dir, ignore_errors=True)
    return counts[0], counts[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--examples", type=int, default=500, help="examples per target")
    ap.add_argument("--target", default="all", choices=sorted(set(fz.TARGETS) | set(ALIASES)))
    ap.add_argument("--save", required=True, help="folder for the inputs of failures")
    ap.add_argument("--seed", type=int, help="hypothesis seed (default: random)")
    ap.add_argument("--scene", help="a fastneus scene to start from (default: synthesise the tests' small scene)")
    a = ap.parse_args(argv)
    save = Path(a.save)
    save.mkdir(parents=True, exist_ok=True)
    targets = ALIASES.get(a.target, (a.target,))
    with tempfile.TemporaryDirectory(prefix="fastneus-fuzz-") as tmp:
        tmp = Path(tmp)
        scene = Path(a.scene) if a.scene else fz.synth_scene(tmp / "sphere3")
        f = fz.Fuzz(fz.build_bases(tmp / "bases", scene), tmp / "work")
        found: dict[str, Path] = {}
        for t in targets:
            t0 = time.perf_counter()
            n, errs = run_target(f, t, a.examples, a.seed, save, found)
            print(f"{t}: {n} examples, {errs} refused with a FastneusError, {n - errs} loaded "
                  f"(or failed: see above), {time.perf_counter() - t0:.1f} s", flush=True)
    print(f"{len(found)} distinct failure(s)" + (f"; inputs under {save}" if found else ""))
    for cause, d in found.items():
        print(f"  {cause}: {d}")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
