"""``bimacppo-select``: choose a run's checkpoint on validation seeds.

A run's last checkpoint is one draw among several policies of similar quality: one cell's
success moves by 5-13 points between checkpoints a few hundred episodes apart, and the training
success, dominated by the cells the curriculum samples most, does not show which cell moved
(docs/results.md, "Checkpoints chosen on validation seeds"). Choosing among a run's checkpoints is
a choice, so it is made on the **validation** scenario seeds only (the tool has no way to use the
test set), and the policy it writes records which checkpoint it is and how it was chosen.

Two criteria:

* ``worst-cell`` (default): the highest success in the run's worst cell, then the highest mean.
  The method's targets are per cell (every task at every N_sv), so a policy that fails one
  cell is not rescued by the others.
* ``mean``: the highest mean success over the cells, then the best worst cell.

Remaining ties go to the checkpoint with more training. With 30 episodes per cell one episode
is 3.3 points, and a cell at 95 % over 100 episodes has a standard error of 2.2 points: the
choice reliably avoids a checkpoint with a systematic failure (an empty-road cell at 90 %), not
one that is a few points worse. It stays unbiased for the test set, which never enters it.
"""
from __future__ import annotations

import argparse
import csv
import io
import pathlib
import sys
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Sequence

CRITERIA = ("worst-cell", "mean")


@dataclass(frozen=True)
class Candidate:
    """One checkpoint's validation cells: success % per (task, N_sv)."""
    path: pathlib.Path
    episodes: int
    success: dict   # (task, n_sv) -> success %

    @property
    def worst(self) -> float:
        return min(self.success.values())

    @property
    def mean(self) -> float:
        return sum(self.success.values()) / len(self.success)


def rank_key(c: Candidate, criterion: str) -> tuple:
    """Sort key, larger is better (see the module docstring for the rule)."""
    if criterion == "worst-cell":
        return (c.worst, c.mean, c.episodes)
    if criterion == "mean":
        return (c.mean, c.worst, c.episodes)
    raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")


def choose(candidates: Sequence[Candidate], criterion: str = "worst-cell") -> Candidate:
    """The best candidate under ``criterion``; ValueError for none or mismatched cells."""
    if not candidates:
        raise ValueError("no checkpoints to choose from")
    cells = set(candidates[0].success)
    for c in candidates[1:]:
        if set(c.success) != cells:
            raise ValueError(f"{c.path}: evaluated on other cells than {candidates[0].path}")
    return max(candidates, key=lambda c: rank_key(c, criterion))


def candidate_checkpoints(run_dir: str | pathlib.Path, from_episodes: int = 0) -> list[tuple[int, pathlib.Path]]:
    """(episodes, path) of every checkpoint in ``run_dir/checkpoints`` with at least
    ``from_episodes`` episodes, oldest first. ValueError naming the directory when there is none."""
    from .checkpoint import list_checkpoints_by_episodes

    run_dir = pathlib.Path(run_dir)
    ckpt_dir = run_dir / "checkpoints"
    if not ckpt_dir.is_dir():
        raise ValueError(f"{run_dir}: no checkpoints/ directory (is it a bimacppo-train run directory?)")
    found = list_checkpoints_by_episodes(ckpt_dir)
    if not found:
        raise ValueError(f"{ckpt_dir}: holds no checkpoint files (ckpt_ep<episodes>.pt)")
    kept = [(e, p) for e, p in found if e >= from_episodes]
    if not kept:
        raise ValueError(f"{ckpt_dir}: no checkpoint has >= {from_episodes} episodes (the last has {found[-1][0]})")
    return kept


def score_checkpoints(checkpoints: Iterable[tuple[int, pathlib.Path]], *, n_svs: Sequence[int],
                      tasks: Sequence[int], episodes: int, workers: int = 2, action_selection: str = "median",
                      mpc_config: Any = None, map_id: str = "dual_lane_4way", slow_svs: int = 0,
                      progress: Callable[[pathlib.Path, Any], None] | None = None,
                      seed_set: str = "validation") -> list[Candidate]:
    """Evaluate every checkpoint on a validation seed set (the same scenarios for each); a test
    set is refused (ValueError), since it never chooses."""
    from .evaluate import evaluate
    from .seed_sets import CHOOSING_SETS

    if seed_set not in CHOOSING_SETS:
        raise ValueError(f"seed set {seed_set!r} only reports; choose on one of {list(CHOOSING_SETS)}")
    out = []
    for ep, path in checkpoints:
        cells = evaluate(str(path), map_id, n_svs, tasks, episodes, workers, random_row=False,
                         seed_set=seed_set, mpc_config=mpc_config, action_selection=action_selection,
                         slow_svs=slow_svs,
                         progress=(lambda cell, path=path: progress(path, cell)) if progress else None)
        out.append(Candidate(pathlib.Path(path), int(ep), {(c.task, c.n_sv): c.pct("success") for c in cells}))
    return out


def table_markdown(candidates: Sequence[Candidate], chosen: Candidate, criterion: str) -> str:
    from bimacppo_common.conventions import TASKS

    cells = sorted(candidates[0].success, key=lambda tn: (tn[1], tn[0]))   # N_sv-major, as evaluation tables
    head = ["checkpoint (episodes)", *[f"N_sv={n} {TASKS[t]}" for t, n in cells], "worst", "mean"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for c in candidates:
        mark = " **chosen**" if c is chosen else ""
        row = [f"{c.episodes}{mark}", *[f"{c.success[k]:.0f}" for k in cells], f"{c.worst:.0f}", f"{c.mean:.1f}"]
        lines.append("| " + " | ".join(row) + " |")
    lines.append("")
    lines.append(f"Validation seeds, success %; criterion: {criterion}.")
    return "\n".join(lines)


def table_csv(candidates: Sequence[Candidate]) -> str:
    from bimacppo_common.conventions import TASKS

    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["checkpoint", "episodes", "task", "n_sv", "success_pct"])
    for c in candidates:
        for (t, n), s in sorted(c.success.items()):
            w.writerow([c.path.name, c.episodes, TASKS[t], n, f"{s:.2f}"])
    return buf.getvalue()


def plot(candidates: Sequence[Candidate], chosen: Candidate, path: str | pathlib.Path, title: str = "") -> None:
    """Validation success per cell over the checkpoints, the chosen one marked."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from bimacppo_common.conventions import TASKS

    eps = [c.episodes for c in candidates]
    fig, ax = plt.subplots(figsize=(7, 3.6))
    for key in sorted(candidates[0].success, key=lambda tn: (tn[1], tn[0])):
        ax.plot(eps, [c.success[key] for c in candidates], marker="o", ms=3,
                label=f"{TASKS[key[0]]}, N_sv={key[1]}")
    ax.plot(eps, [c.worst for c in candidates], color="k", lw=2, label="worst cell")
    ax.axvline(chosen.episodes, color="k", ls=":", lw=1)
    ax.set_xlabel("training episodes (checkpoint)")
    ax.set_ylabel("validation success (%)")
    ax.set_title(title or "checkpoints on validation seeds")
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _parser() -> argparse.ArgumentParser:
    from .cli import add_protocol_arguments
    from .seed_sets import CHOOSING_SETS

    p = argparse.ArgumentParser(
        prog="bimacppo-select",
        description="Evaluate a training run's checkpoints on the validation scenario seeds and write the "
                    "best one as a policy file that records how it acts and how it was chosen. The test "
                    "seeds are never used.")
    p.add_argument("run_dir", type=pathlib.Path, help="a bimacppo-train run directory (with checkpoints/)")
    p.add_argument("out", type=pathlib.Path, help="the chosen policy file to write (must not exist)")
    p.add_argument("--from-episodes", type=int, default=0,
                   help="consider only checkpoints with at least this many episodes (default: all)")
    p.add_argument("--criterion", choices=CRITERIA, default="worst-cell",
                   help="worst-cell: best worst cell, then best mean (default); mean: the reverse")
    add_protocol_arguments(p, episodes=30, episodes_help="validation episodes per cell, 1..1000 (default 30)",
                           n_svs=[0, 3])
    p.add_argument("--action", choices=("argmax", "median"), default="median",
                   help="how the policies act while evaluated; the written policy records it (default median)")
    p.add_argument("--mpc-config", type=pathlib.Path, default=None,
                   help="YAML overlaying the packaged mpc.yaml (default: the one each checkpoint records)")
    p.add_argument("--table", type=pathlib.Path, default=None,
                   help="also write TABLE.md, TABLE.csv (success per checkpoint and cell) and TABLE.png")
    p.add_argument("--seed-set", choices=CHOOSING_SETS, default="validation",
                   help="the validation set that chooses: validation (default) or validation2, the second "
                        "pair's, for a choice made afresh; the test sets never choose")
    return p


def main(argv=None) -> int:
    args = _parser().parse_args(argv)
    from bimacppo_common.conventions import TASKS
    from bimacppo_planner.decision import ConfigError

    from .checkpoint import CheckpointError, set_action_selection
    from .cli import fail, protocol_tasks
    from .evaluate import EvaluationError, resolve_policy

    prog = "bimacppo-select"
    try:
        tasks = protocol_tasks(args)
    except ValueError as exc:
        return fail(prog, exc)
    if args.out.exists():
        return fail(prog, f"{args.out}: exists; a policy file is not overwritten (choose another name)")
    if args.table is not None:
        for suffix in (".md", ".csv", ".png"):
            if args.table.with_name(args.table.name + suffix).exists():
                return fail(prog, f"{args.table}{suffix}: exists; choose another --table prefix")
    try:
        ckpts = candidate_checkpoints(args.run_dir, args.from_episodes)
        for _, path in ckpts:   # every file readable before the first episode runs
            resolve_policy(str(path))
    except (ValueError, CheckpointError, EvaluationError, ConfigError) as exc:
        return fail(prog, exc)
    from tqdm.auto import tqdm

    bar = tqdm(total=len(ckpts) * len(tasks) * len(args.n_sv), unit="cell", desc="validating", disable=None)

    def progress(path, cell):
        bar.update(1)
        bar.set_postfix_str(f"{path.name} {TASKS[cell.task]} N_sv={cell.n_sv}: S={cell.pct('success'):.0f}%")

    try:
        cands = score_checkpoints(ckpts, n_svs=args.n_sv, tasks=tasks, episodes=args.episodes,
                                  workers=args.workers, action_selection=args.action,
                                  mpc_config=args.mpc_config, map_id=args.map, slow_svs=args.slow_svs,
                                  progress=progress, seed_set=args.seed_set)
    except (CheckpointError, EvaluationError, ConfigError, ValueError) as exc:
        return fail(prog, exc)
    finally:
        bar.close()
    best = choose(cands, args.criterion)
    record = {"checkpoint": best.path.name, "episodes": best.episodes, "criterion": args.criterion,
              "seed_set": args.seed_set, "episodes_per_cell": args.episodes, "map": args.map,
              "slow_svs": args.slow_svs,
              "n_sv": list(args.n_sv), "tasks": list(args.tasks), "worst_cell": best.worst, "mean": best.mean,
              "candidates": len(cands)}
    try:
        set_action_selection(best.path, args.out, args.action, meta={"chosen_on_validation": record})
    except (CheckpointError, FileExistsError, ValueError) as exc:
        return fail(prog, exc)
    md = table_markdown(cands, best, args.criterion)
    print(md)
    if args.table is not None:
        args.table.parent.mkdir(parents=True, exist_ok=True)
        args.table.with_name(args.table.name + ".md").write_text(md + "\n")
        args.table.with_name(args.table.name + ".csv").write_text(table_csv(cands))
        plot(cands, best, args.table.with_name(args.table.name + ".png"), title=str(args.run_dir))
    print(f"chose {best.path.name} ({best.episodes} episodes; worst cell {best.worst:.0f} %, mean {best.mean:.1f} %)"
          f"; wrote {args.out} (acts by {args.action})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
