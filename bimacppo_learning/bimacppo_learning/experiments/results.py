"""The results page: Tables I-III, Figs. 5-6, success curves and sample efficiency as markdown
and PNGs, from whatever runs and evaluations exist; what is missing is listed, never invented."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from bimacppo_common.conventions import TASKS

from .config import METHOD_NAMES, ExperimentConfig
from .runs import eval_is_fresh, read_eval_csv, read_history, run_status
from .stats import (aggregate_cells, episodes_to_fraction, improvement_probability, iqm_intervals, mean_counts,
                    mean_std_curve, success_matrix)
from .train import train_argv


def pm(mean: float, std: float) -> str:
    return f"{mean:.0f}" if not np.isfinite(std) else f"{mean:.0f}±{std:.0f}"


def table_markdown(rows: list[tuple[str, dict, int]], cfg: ExperimentConfig) -> str:
    """Table II/III layout: rows = method x task, columns = N_sv, cells S / C / TO (%) as
    mean±std over seeds (a single seed or a scripted driver: the value alone)."""
    nsv = list(cfg.evaluation.n_sv)
    lines = ["| method | task | " + " | ".join(f"N_sv={n} S / C / TO (%)" for n in nsv) + " | seeds |",
             "|---|---|" + "---|" * len(nsv) + "---|"]
    for name, agg, n_runs in rows:
        for t in cfg.evaluation.tasks:
            j = TASKS.index(t)
            cells = []
            for n in nsv:
                c = agg.get((j, n))
                cells.append("–" if c is None else " / ".join(pm(c["mean"][k], c["std"][k]) for k in range(3)))
            lines.append(f"| {name} | {t} | " + " | ".join(cells) + f" | {n_runs or 'scripted'} |")
    return "\n".join(lines)


RANDOM_POLICY = "random policy"


def random_policy_table(cfg: ExperimentConfig, done: Mapping, map_id: str):
    """The uniform random policy's cells on ``map_id``: ``bimacppo-evaluate`` writes them next to
    every policy's evaluation (``<prefix>_random.csv``, same scenarios); the first evaluated run's
    file is used (every run of a grid shares the env config, so they agree). None if none exists."""
    for key in sorted(done):
        prefix = cfg.eval_prefix(done[key].run_dir, map_id)
        path = prefix.with_name(prefix.name + "_random.csv")
        if path.is_file():
            return read_eval_csv(path)
    return None


def aggregate_markdown(scores: Mapping[str, list], cfg: ExperimentConfig, reps: int) -> str:
    """Success aggregated over training seeds x evaluation cells with rliable: IQM and mean, each
    with its stratified bootstrap 95 % interval, and the probability that BiM-ACPPO improves on
    each other row (a scripted driver is one run)."""
    cells = [(TASKS.index(t), n) for t in cfg.evaluation.tasks for n in cfg.evaluation.n_sv]
    mats = {name: success_matrix(tables, cells) for name, tables in scores.items()}
    est = iqm_intervals(mats, reps=reps)
    lines = [f"Success (%) over runs x {len(cells)} cells (rliable, stratified bootstrap, {reps} resamples, "
             "95 % intervals):", "",
             "| method | runs | IQM [95 % CI] | mean [95 % CI] | P(BiM-ACPPO > method) [95 % CI] |",
             "|---|---|---|---|---|"]
    ours = METHOD_NAMES["bimab"]
    for name, e in est.items():
        poi = "–"
        if ours in mats and name != ours:
            pr = improvement_probability(mats[ours], mats[name], reps=reps)
            poi = f"{pr['p']:.2f} [{pr['ci'][0]:.2f}, {pr['ci'][1]:.2f}]"
        lines.append(f"| {name} | {e['runs']} | {e['iqm']:.1f} [{e['iqm_ci'][0]:.1f}, {e['iqm_ci'][1]:.1f}] | "
                     f"{e['mean']:.1f} [{e['mean_ci'][0]:.1f}, {e['mean_ci'][1]:.1f}] | {poi} |")
    return "\n".join(lines)


def counts_markdown(counts: Mapping[str, float]) -> str:
    n = 0
    while f"count_{n}" in counts:
        n += 1
    lines = ["| N_sv | sampled | " + " | ".join(f"{t} (j={j})" for j, t in enumerate(TASKS)) + " |",
             "|---:|---:|" + "---:|" * len(TASKS)]
    tot = np.zeros(len(TASKS))
    for i in range(n):
        arms = np.array([counts.get(f"count_{i}_{j}", 0.0) for j in range(len(TASKS))])
        tot += arms
        lines.append(f"| {i} | {counts[f'count_{i}']:.1f} | " + " | ".join(f"{a:.1f}" for a in arms) + " |")
    lines.append(f"| all | {tot.sum():.1f} | " + " | ".join(f"{a:.1f}" for a in tot) + " |")
    return "\n".join(lines)


def image_path(cfg: ExperimentConfig, name: str) -> Path:
    return Path(f"{cfg.img_prefix}_{name}.png")


def relative_to_page(path: Path, md: Path) -> str:
    return os.path.relpath(path, md.parent)


def report(cfg: ExperimentConfig, config_arg: str | None = None) -> dict:
    """Write the results page (+ PNGs) from whatever exists; returns {"path", "missing"}."""
    from bimacppo_curriculum import plots

    md_path = Path(cfg.results_md)
    md_path.parent.mkdir(parents=True, exist_ok=True)
    Path(cfg.img_prefix).parent.mkdir(parents=True, exist_ok=True)
    r = cfg.report
    missing: list[str] = []
    status = {(m, s): run_status(cfg, m, s) for m in cfg.methods for s in cfg.seeds}
    done = {k: v for k, v in status.items() if v.done}
    for (m, s), st in status.items():
        if not st.done:
            missing.append(f"training run `{m}-s{s}`: {st.state} ({st.episodes}/{cfg.episodes} episodes) "
                           f"in `{st.run_dir}`")
    hist = {k: read_history(v.run_dir) for k, v in done.items()}
    cfg_flag = f" --config {config_arg}" if config_arg else ""
    out = [f"# Experiment results (generated by `bimacppo-experiments{cfg_flag} report`)", "",
           f"Generated from the runs under `{cfg.runs_dir}` with the config `{cfg.source}`: "
           f"{len(cfg.methods)} methods x seeds {list(cfg.seeds)}, {cfg.episodes} training episodes each on "
           f"`{cfg.train_map}`, evaluation {cfg.evaluation.episodes} episodes per task x N_sv cell on the fixed "
           "seeds of `bimacppo_learning.evaluate.eval_seed` (shared by every method and by the scripted drivers). "
           "Numbers below are read from those files; nothing is typed in. Cells are S / C / TO in percent, "
           "mean±std (sample std, ddof=1) over the training seeds that finished and were evaluated.", "",
           "## Runs", "", "| method | " + " | ".join(f"seed {s}" for s in cfg.seeds) + " |",
           "|---|" + "---|" * len(cfg.seeds)]
    for m in cfg.methods:
        out.append(f"| {METHOD_NAMES[m]} | " + " | ".join(
            f"{status[(m, s)].state} ({status[(m, s)].episodes})" for s in cfg.seeds) + " |")
    # --- Tables II and III
    for title, map_id in (("Table II: success / collision / timeout on", cfg.train_map),
                          ("Table III: zero-shot on", cfg.zero_shot_map)):
        if map_id is None:
            continue
        rows, scores = [], {}
        for m in cfg.methods:
            tables = []
            for s in cfg.seeds:
                if (m, s) not in done:
                    continue
                p = cfg.eval_prefix(done[(m, s)].run_dir, map_id).with_suffix(".csv")
                if eval_is_fresh(cfg, p, done[(m, s)].run_dir / "policy.pt"):
                    tables.append(read_eval_csv(p))
                else:
                    missing.append(f"evaluation of `{m}-s{s}` on `{map_id}` (`{p}`)")
            if tables:
                rows.append((METHOD_NAMES[m], aggregate_cells(tables), len(tables)))
                scores[METHOD_NAMES[m]] = tables
        for d in cfg.evaluation.reference_drivers:
            p = cfg.reference_prefix(d, map_id).with_suffix(".csv")
            if eval_is_fresh(cfg, p, None):
                table = read_eval_csv(p)
                rows.append((METHOD_NAMES[d], aggregate_cells([table]), 0))
                scores[METHOD_NAMES[d]] = [table]
            else:
                missing.append(f"scripted driver `{d}` on `{map_id}` (`{p}`)")
        rand = random_policy_table(cfg, done, map_id)
        if rand is not None:
            rows.append((RANDOM_POLICY, aggregate_cells([rand]), "one evaluation"))
            scores[RANDOM_POLICY] = [rand]
        out += ["", f"## {title} `{map_id}`", ""]
        out.append(table_markdown(rows, cfg) if rows else "_no evaluated runs yet_")
        out.append("")
        out.append("`seeds` = training seeds averaged; scripted drivers are deterministic (one evaluation); "
                   f"the {RANDOM_POLICY} acts uniformly at random on the same scenarios (one evaluation, written "
                   "with the first evaluated run's).")
        if scores:
            out += ["", aggregate_markdown(scores, cfg, r.bootstrap_reps)]
    # --- Table I, Figs. 5-6
    bimab = [s for s in cfg.seeds if ("bimab", s) in done]
    out += ["", "## Table I: BiMAB sampled counts (mean over BiM-ACPPO seeds)", ""]
    if bimab:
        out.append(f"Mean over seeds {bimab} of the scheduler's final counts.")
        out += ["", counts_markdown(mean_counts([hist[("bimab", s)][-1]["scheduler"] for s in bimab]))]
        fs = r.figure_seed if r.figure_seed in bimab else bimab[0]
        h = [dict(rec["scheduler"], episodes=rec["episode"]) for rec in hist[("bimab", fs)]]
        f5 = plots.plot_cluster_weights(h, image_path(cfg, "fig5_clusters"), f"BiM-ACPPO seed {fs}: cluster weights (Fig. 5)")
        f6 = plots.plot_arm_weights(h, image_path(cfg, "fig6_arms"), f"BiM-ACPPO seed {fs}: arm weights (Fig. 6)")
        out += ["", f"## Figs. 5-6: BiMAB weights (BiM-ACPPO seed {fs})", "",
                f"![Fig. 5]({relative_to_page(f5, md_path)})", "", f"![Fig. 6]({relative_to_page(f6, md_path)})"]
    else:
        out.append("_no finished BiM-ACPPO run yet_")
    # --- success curves and sample efficiency
    curves, eff_rows = {}, []
    for m in cfg.methods:
        seeds = [s for s in cfg.seeds if (m, s) in done]
        if not seeds:
            continue
        c = mean_std_curve([hist[(m, s)] for s in seeds], r.window)
        if c is not None:
            curves[f"{METHOD_NAMES[m]} ({len(seeds)} seeds)"] = c
        per = [episodes_to_fraction(hist[(m, s)], r.window, r.efficiency_fraction) for s in seeds]
        reach = [e for e, _ in per if e is not None]
        finals = np.array([100 * f for _, f in per], float)
        fin = finals[np.isfinite(finals)]
        eff_rows.append(
            f"| {METHOD_NAMES[m]} | {len(seeds)} | "
            + (pm(fin.mean(), fin.std(ddof=1) if len(fin) > 1 else np.nan) if len(fin) else "–") + " | "
            + (pm(np.mean(reach), np.std(reach, ddof=1) if len(reach) > 1 else np.nan) if reach else "–") + " | "
            + ", ".join("–" if e is None else str(e) for e, _ in per) + " |")
    out += ["", "## Training success and sample efficiency", ""]
    if curves:
        f = plots.plot_curves(curves, image_path(cfg, "success"), f"success rate (last {r.window} episodes)",
                              "Training success rate, mean ± std over seeds")
        out += [f"![success curves]({relative_to_page(f, md_path)})", "",
                f"Rolling success over the last {r.window} training episodes (shown once a full window "
                "exists), mean over seeds with a ±1 std band, on the episodes every seed has.", "",
                f"Sample efficiency: the first episode at which a run's rolling success ({r.window}-episode "
                f"window) reaches {r.efficiency_fraction:.0%} of its own final rolling success (the value at "
                "its last episode); – = final success 0 or no full window.", "",
                f"| method | seeds | final success (%) | episodes to {r.efficiency_fraction:.0%} of final | per seed |",
                "|---|---|---|---|---|", *eff_rows]
    else:
        out.append("_no finished training run yet_")
    # --- overtaking
    o = cfg.overtake
    out += ["", f"## Overtaking on `{o.map}` (fine-tuned {METHOD_NAMES[o.source_method]}, paper §IV-C)", ""]
    tests = sorted(Path(cfg.runs_dir, o.map).glob(f"{o.source_method}-s*-finetune/test.json"))
    if tests:
        for tp in tests:
            t = json.loads(tp.read_text())
            out.append(f"- `{tp.parent.name}` (from {t.get('source')}, {t.get('source_reason', '')}): "
                       f"{t['episodes']} tests with {t['n_sv']} SVs (slow SVs per test: {t['n_slow_counts']}): "
                       f"success {t['success_pct']:.0f}%, collision {t['collision_pct']:.0f}%, "
                       f"timeout {t['timeout_pct']:.0f}%")
    else:
        out.append("_not run yet_")
        missing.append(f"overtaking fine-tune + tests (`{Path(cfg.runs_dir, o.map)}`)")
    # --- commands and missing
    c = f"bimacppo-experiments{cfg_flag}"
    out += ["", "## Commands", "", "```bash",
            f"{c} all          # everything below, skipping what is done",
            f"{c} train        # each run = bimacppo-train " + " ".join(train_argv(cfg, "<method>", "<seed>", False)),
            f"{c} evaluate     # bimacppo-evaluate protocol per run on {', '.join(cfg.eval_maps())} + scripted drivers",
            f"{c} overtake     # fine-tune the best {o.source_method} seed on {o.map}, {o.episodes} episodes; {o.test_episodes} tests",
            f"{c} report       # this page", "```", "", "## Missing", ""]
    out += [f"- {x}" for x in missing] if missing else ["Nothing: every run, evaluation and test exists."]
    md_path.write_text("\n".join(out) + "\n")
    return {"path": str(md_path), "missing": missing}
