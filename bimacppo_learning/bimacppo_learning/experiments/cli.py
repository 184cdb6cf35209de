"""``bimacppo-experiments``: the command line over the steps (train, evaluate, overtake, report)."""
from __future__ import annotations

import argparse
import sys

from .config import CURRICULA, ExperimentError, load_experiment_config
from .evaluation import evaluate_all
from .overtake import overtake
from .results import report
from .train import train

def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bimacppo-experiments", description=sys.modules[__package__].__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="YAML with the keys of config/experiments.yaml to change")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train every missing run (resume unfinished ones), one at a time")
    t.add_argument("--only", nargs="+", metavar="METHOD", help=f"methods among {list(CURRICULA)}")
    t.add_argument("--seeds", nargs="+", type=int, help="seeds (default: the config's)")
    sub.add_parser("evaluate", help="paper protocol for every finished run (training + zero-shot map) and the scripted drivers")
    sub.add_parser("overtake", help="fine-tune the best BiM-ACPPO seed on the 3-lane road, then the tests")
    sub.add_parser("report", help="write the results page and figures from what exists")
    sub.add_parser("all", help="train -> evaluate -> overtake -> report")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_experiment_config(args.config)
        rc = 0
        if args.cmd in ("train", "all"):
            rc |= int(train(cfg, getattr(args, "only", None), getattr(args, "seeds", None)) > 0)
        if args.cmd in ("evaluate", "all"):
            evaluate_all(cfg)
        if args.cmd in ("overtake", "all"):
            try:
                overtake(cfg)
            except ExperimentError as exc:
                if args.cmd == "overtake":
                    raise
                print(f"overtaking skipped: {exc}")
        if args.cmd in ("report", "all"):
            res = report(cfg, args.config)
            print(f"wrote {res['path']} ({len(res['missing'])} item(s) missing)")
        return rc
    except ExperimentError as exc:
        print(f"bimacppo-experiments: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
