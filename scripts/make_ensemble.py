"""Write an ensemble policy file: several policies trained alike (other training seeds of one
configuration) that act as one, each head on the mixture of the members' distributions
(``bimacppo_planner.policy.EnsemblePolicy``), or, with ``--combine vote``, by the value most
members choose. The planner node and ``bimacppo-evaluate`` take the file like any policy file.

    python scripts/make_ensemble.py ensemble.pt runs/<run>_s0/policy.pt runs/<run>_s1/policy.pt runs/<run>_s2/policy.pt
"""
from __future__ import annotations

import argparse
import sys

from bimacppo_learning.checkpoint import make_ensemble
from bimacppo_planner.policy import DEPLOYED_SELECTIONS, ENSEMBLE_COMBINES, CheckpointError


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dst", help="the new ensemble file (must not exist)")
    p.add_argument("members", nargs="+", help="policy exports (policy.pt) or training checkpoints, at least 2")
    p.add_argument("--action", choices=DEPLOYED_SELECTIONS, default="median",
                   help="how the ensemble acts when deployed (default: median)")
    p.add_argument("--combine", choices=ENSEMBLE_COMBINES, default="mixture",
                   help="the members' mixture decides each head (default), or their vote (ties: the mixture)")
    args = p.parse_args(argv)
    try:
        out = make_ensemble(args.members, args.dst, args.action, args.combine)
    except (CheckpointError, FileExistsError, ValueError) as exc:
        print(f"make_ensemble: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    how = "mixture" if args.combine == "mixture" else "members, voted"
    print(f"wrote {out}: {len(args.members)} members, acts by the {args.action} of their {how}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
