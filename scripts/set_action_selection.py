"""Write a copy of a policy file that records how it acts when deployed (argmax or median):
the planner node and ``bimacppo-evaluate`` then run it that way unless told otherwise.

    python scripts/set_action_selection.py runs/<run>/policy.pt chosen.pt --action median

``--fine-tuned-from SOURCE`` also records the file the policy's run started from
(``fine_tuned_from``, as ``bimacppo-train --init-policy`` records it), for a policy whose run
did not record it; a policy that records one already is refused.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping

from bimacppo_learning.checkpoint import (check_checkpoint, checkpoint_meta, fine_tune_source_record,
                                          set_action_selection)
from bimacppo_planner.policy import (CHECKPOINT_FORMAT, DEPLOYED_SELECTIONS, CheckpointError, Policy,
                                     read_policy_payload, read_torch_file)


def _source_record(src: str, source: str) -> dict:
    """The lineage record of ``source`` for the policy ``src``: CheckpointError if ``src``
    already records a lineage or ``source`` is no usable policy export or training checkpoint."""
    d = read_policy_payload(src)
    if isinstance(d, Mapping) and isinstance(d.get("meta"), Mapping) and d["meta"].get("fine_tuned_from") is not None:
        raise CheckpointError(src, "records the file it was fine-tuned from already")
    s = read_torch_file(source)
    if isinstance(s, Mapping) and s.get("format") == CHECKPOINT_FORMAT:
        meta = checkpoint_meta(check_checkpoint(s, source), source)
    else:
        meta = dict(Policy(s, source).meta)
    return fine_tune_source_record(source, meta)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("src", help="a policy export (policy.pt) or a training checkpoint")
    p.add_argument("dst", help="the new policy file (must not exist)")
    p.add_argument("--action", choices=DEPLOYED_SELECTIONS, required=True)
    p.add_argument("--fine-tuned-from", metavar="SOURCE", default=None,
                   help="the policy file or checkpoint the run of SRC started from (recorded with its SHA-256)")
    args = p.parse_args(argv)
    try:
        meta = None if args.fine_tuned_from is None else {
            "fine_tuned_from": _source_record(args.src, args.fine_tuned_from)}
        out = set_action_selection(args.src, args.dst, args.action, meta=meta)
    except (CheckpointError, FileExistsError, ValueError, OSError) as exc:
        print(f"set_action_selection: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {out} (acts by {args.action})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
