"""``bimacppo-experiments``: the command line over the steps (train, evaluate, overtake, report).

Exit codes: 0 everything asked for exists; 1 some run, evaluation or test failed (each
reported on one line with its log; the others went on); 2 a problem to fix before anything
runs (config, method names, corrupt history, no Ray cluster at ``--address``), printed as one
``bimacppo-experiments: error: ...`` line.
"""
from __future__ import annotations

import argparse
import sys

from bimacppo_common.config import ConfigError

from .config import CURRICULA, ExperimentError, load_experiment_config
from .evaluation import evaluate_all
from .overtake import overtake
from .pool import Cluster
from .results import report
from .train import train


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="bimacppo-experiments", description=sys.modules[__package__].__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default=None, help="YAML with the keys of config/experiments.yaml to change")
    p.add_argument("--address", default=None,
                   help="Ray cluster to run on (`auto` = the one `ray start` set up on this machine, or "
                        "HOST:PORT of its head); default: start a local Ray for this command")
    p.add_argument("--num-cpus", type=int, default=None,
                   help="CPUs of the local Ray (default: all of this machine's); not with --address")
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("train", help="train every run not done (resume unfinished ones), as many at once as the CPUs allow")
    t.add_argument("--only", nargs="+", metavar="METHOD", help=f"methods among {list(CURRICULA)}")
    t.add_argument("--seeds", nargs="+", type=int, help="seeds (default: the config's)")
    sub.add_parser("evaluate", help="paper protocol for every finished run (training + zero-shot map) and the scripted drivers")
    sub.add_parser("overtake", help="fine-tune the best BiM-ACPPO seed on the 3-lane road, then the tests")
    sub.add_parser("report", help="write the results page and figures from what exists")
    sub.add_parser("all", help="train -> evaluate -> overtake -> report")
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.num_cpus is not None and args.num_cpus < 1:
        print("bimacppo-experiments: error: --num-cpus must be >= 1", file=sys.stderr)
        return 2
    cluster = Cluster(args.address, args.num_cpus)
    try:
        cfg = load_experiment_config(args.config)
        rc = 0
        if args.cmd in ("train", "all"):
            rc |= int(train(cfg, getattr(args, "only", None), getattr(args, "seeds", None), cluster=cluster) > 0)
        if args.cmd in ("evaluate", "all"):
            rc |= int(evaluate_all(cfg, cluster=cluster) > 0)
        if args.cmd in ("overtake", "all"):
            try:
                rc |= int(overtake(cfg, cluster=cluster) is None)
            except ExperimentError as exc:
                if args.cmd == "overtake":
                    raise
                print(f"overtaking skipped: {exc}")
        if args.cmd in ("report", "all"):
            res = report(cfg, args.config)
            print(f"wrote {res['path']} ({len(res['missing'])} item(s) missing)")
        return rc
    except (ExperimentError, ConfigError) as exc:
        print(f"bimacppo-experiments: error: {exc}", file=sys.stderr)
        return 2
    finally:
        cluster.close()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
