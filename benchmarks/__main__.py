"""``python -m benchmarks [--quick] [--out DIR] [--only A,B]``: run every section (or the
named ones), write DIR/RESULTS.md + PNGs.

A section that fails is reported as failed (with the error) rather than stopping the run,
so one broken peer (say, an open3d that will not import) does not lose the other sections.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
import traceback
from pathlib import Path

from benchmarks import (accuracy, depth, engine, geo, heldout, memory, noisy, pipeline, report, tiles,
                        triangulation)
from benchmarks.common import Config, Section

SECTIONS = (engine, pipeline, triangulation, accuracy, noisy, memory, tiles, geo, depth, heldout)


def _output_folder(out: Path | None, quick: bool) -> Path:
    """Where RESULTS.md and the plots go: the folder asked for; else benchmarks/ for a full
    run, and a fresh temporary folder for --quick (its small sizes are not results)."""
    if out is not None:
        return out
    if quick:
        return Path(tempfile.mkdtemp(prefix="c1mesh-bench-quick-"))
    return Path(__file__).resolve().parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, < ~60 s (smoke test)")
    parser.add_argument("--out", type=Path, default=None,
                        help="directory for RESULTS.md and the PNGs (default: benchmarks/ for a full "
                             "run; a new temporary folder for --quick, so a smoke run never "
                             "overwrites the committed results)")
    parser.add_argument("--only", help="comma-separated section names to run (e.g. pipeline,depth); "
                                        "default: all")
    args = parser.parse_args(argv)
    sections_to_run = _chosen(args.only, parser)
    args.out = _output_folder(args.out, args.quick)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = Config.make(args.quick, args.out)
    command = " ".join(["python -m benchmarks", *(sys.argv[1:] if argv is None else argv)])
    start, sections, failed = time.perf_counter(), [], 0
    for mod in sections_to_run:
        t = time.perf_counter()
        print(f"[benchmarks] {mod.__name__} ...", file=sys.stderr, flush=True)
        try:
            sec = mod.run(cfg)
        except Exception:  # noqa: BLE001 - report the failure, keep the other sections
            failed += 1
            sec = Section(f"{mod.__name__.split('.')[-1]}: FAILED")
            sec.add("```", traceback.format_exc().strip()[-2000:], "```")
            traceback.print_exc()
        sec.add(f"_Section time: {time.perf_counter() - t:.0f} s._")
        sections.append(sec)
        print(f"[benchmarks] {mod.__name__} done in {time.perf_counter() - t:.0f} s",
              file=sys.stderr, flush=True)
    report.write(args.out / "RESULTS.md", command, args.quick, sections, time.perf_counter() - start)
    print(f"[benchmarks] wrote {args.out / 'RESULTS.md'}", file=sys.stderr)
    return 1 if failed else 0


def _chosen(only: str | None, parser: argparse.ArgumentParser) -> tuple:
    """The sections named by --only (all without it), in the usual order."""
    if not only:
        return SECTIONS
    names = {mod.__name__.split(".")[-1]: mod for mod in SECTIONS}
    wanted = [name.strip() for name in only.split(",") if name.strip()]
    unknown = [name for name in wanted if name not in names]
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(names)}")
    return tuple(mod for name, mod in names.items() if name in wanted)


if __name__ == "__main__":
    sys.exit(main())
