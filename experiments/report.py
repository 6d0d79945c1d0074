"""Regenerate ``results.json``, the plots and ``significance.md`` of a run directory.

    python experiments/report.py runs/point_goal-20261125-210000
    python experiments/report.py runs/ladder --baseline gmps_ppo      # compare every method with gmps_ppo
    python experiments/report.py runs/ag10 --partial   # a stopped run: the tasks every method has finished
"""

from __future__ import annotations

import argparse
import sys

from jcomps.analysis import report
from jcomps.runner import distributed
from jcomps.runner.files import RunError


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", help="a directory written by experiments/run_sequence.py")
    parser.add_argument("--baseline", default=None, metavar="METHOD",
                        help="the method the significance table compares every other one with (default: comps when "
                             "the run has it)")
    parser.add_argument("--partial", action="store_true",
                        help="report an unfinished run on the tasks every method has finished so far")
    distributed.add_args(parser)
    args = parser.parse_args(argv)
    if not distributed.tool_process(args, parser):
        return
    try:
        results = report.write(args.run_dir, baseline=args.baseline, partial=args.partial)
    except RunError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    for path in results["plots"]:
        print(f"wrote {args.run_dir}/{path}")
    print(f"wrote {args.run_dir}/results.json and {args.run_dir}/significance.md")


if __name__ == "__main__":
    main()
