"""Write a copy of a policy file that records how it acts when deployed (argmax or median):
the planner node and ``bimacppo-evaluate`` then run it that way unless told otherwise.

    python scripts/set_action_selection.py runs/<run>/policy.pt chosen.pt --action median
"""
from __future__ import annotations

import argparse
import sys

from bimacppo_learning.checkpoint import set_action_selection
from bimacppo_planner.policy import DEPLOYED_SELECTIONS, CheckpointError


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", help="a policy export (policy.pt) or a training checkpoint")
    p.add_argument("dst", help="the new policy file (must not exist)")
    p.add_argument("--action", choices=DEPLOYED_SELECTIONS, required=True)
    args = p.parse_args(argv)
    try:
        out = set_action_selection(args.src, args.dst, args.action)
    except (CheckpointError, FileExistsError, ValueError) as exc:
        print(f"set_action_selection: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} (acts by {args.action})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
