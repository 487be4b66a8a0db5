"""``python -m benchmarks [--quick] [--out DIR]``: run every section, write DIR/RESULTS.md + PNGs.

A section that fails is reported as failed (with the error) rather than stopping the run,
so one broken peer (say, an open3d that will not import) does not lose the other sections.
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from pathlib import Path

from benchmarks import accuracy, depth, engine, geo, memory, noisy, pipeline, report, tiles, triangulation
from benchmarks.common import Config, Section

SECTIONS = (engine, pipeline, triangulation, accuracy, noisy, memory, tiles, geo, depth)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("--quick", action="store_true", help="small sizes, < ~60 s (smoke test)")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent,
                        help="directory for RESULTS.md and the PNGs (default: benchmarks/)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    cfg = Config.make(args.quick, args.out)
    command = " ".join(["python -m benchmarks", *(sys.argv[1:] if argv is None else argv)])
    start, sections, failed = time.perf_counter(), [], 0
    for mod in SECTIONS:
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


if __name__ == "__main__":
    sys.exit(main())
