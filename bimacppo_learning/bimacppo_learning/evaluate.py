"""The paper's evaluation protocol (§IV-B): every task x N_sv cell, fixed scenario seeds.

Every method is evaluated on exactly the same scenarios, drawn from the seed sets of
``seed_sets`` (``validation`` for every choice, ``test`` only ever reported).

Any policy can be put through it (``evaluate(policy, ...)``): a policy file (export or training
checkpoint; None = the shipped policy), or an object with ``predict(obs)`` (Stable-Baselines3
style, returning ``(action, state)``; called with ``deterministic=True`` when it takes that) or
``act(obs)``, or a plain callable ``obs -> action``. An action is one integer per MultiDiscrete
head. An object may also have ``begin_episode(scenario_seed)``, called before each episode.

Each cell's success rate comes with its 95 % Wilson score interval (``CI_LEVEL``): with 100
episodes a cell that reads 95 % is consistent with about 89-98 %, and a table that compares
policies or checks a target per cell has to be read with that width in mind.

Beside the policy, a uniform random policy runs on the same cells and scenario seeds (its
actions seeded per episode, so its numbers do not depend on the workers): the floor every table
is read against. Cells run in ``workers`` spawned processes; a failure in any of them ends the
whole evaluation with ``EvaluationError`` (or ``CheckpointError`` for an unusable policy file),
also when a worker dies outright.
"""
from __future__ import annotations

import csv
import inspect
import io
import json
import multiprocessing as mp
import os
import pickle
import queue
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping

import numpy as np

from bimacppo_common.conventions import TASKS
from scipy.stats import binomtest

from bimacppo_planner.policy import CheckpointError

from .comfort import Comfort
from .seed_sets import SEED_SETS, eval_seed

CI_LEVEL = 0.95     # confidence of the per-cell success interval in every table and CSV
POLICY = "policy"          # CellResult.policy of the evaluated policy's cells
RANDOM = "random"          # ... and of the random baseline's


class EvaluationError(Exception):
    """The evaluation could not run; the message is one line naming the cell and the cause."""


@dataclass
class CellResult:
    task: int
    n_sv: int
    counts: Counter
    returns: list
    policy: str = POLICY    # POLICY or RANDOM
    comfort: Comfort | None = None   # ride comfort of the commands applied in the cell's episodes
    threat_entries: int = 0  # episodes in which the EV crossed its stop line into a threatened junction
    seed_set: str = "test"

    @property
    def n(self) -> int:
        return sum(self.counts.values())

    def pct(self, outcome: str) -> float:
        return 100.0 * self.counts.get(outcome, 0) / max(self.n, 1)

    def success_interval(self, level: float = CI_LEVEL) -> tuple[float, float]:
        """Wilson score interval of the success rate in percent (scipy's binomtest); (nan, nan)
        for a cell without episodes. Wilson, not the normal approximation: cells sit near 100 %,
        where the normal interval runs past 100 and collapses to a point at 100 %."""
        if self.n == 0:
            return float("nan"), float("nan")
        ci = binomtest(int(self.counts.get("success", 0)), self.n).proportion_ci(
            confidence_level=level, method="wilson")
        return 100.0 * ci.low, 100.0 * ci.high


class RandomPolicy:
    """Uniform random MultiDiscrete actions; episode k's actions are a function of (seed, its
    scenario seed) only, so every run (any worker count) gets the same random baseline."""

    def __init__(self, nvec: Iterable[int], seed: int = 0):
        self.nvec = np.asarray(list(nvec), np.int64)
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)

    def begin_episode(self, scenario_seed: int) -> None:
        self.rng = np.random.default_rng([self.seed, int(scenario_seed)])

    def act(self, obs) -> np.ndarray:
        return self.rng.integers(0, self.nvec).astype(np.int64)


# ------------------------------------------------------------------ policies
def _takes(fn: Callable, name: str) -> bool:
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == name or p.kind is inspect.Parameter.VAR_KEYWORD for p in params)


def as_actor(policy: Any) -> Callable[[np.ndarray], Any]:
    """``obs -> action`` for a policy object (see the module docstring), deterministic if it can be."""
    for method in ("predict", "act"):
        fn = getattr(policy, method, None)
        if callable(fn):
            kw = {"deterministic": True} if _takes(fn, "deterministic") else {}
            if method == "predict":
                def actor(obs, fn=fn, kw=kw):
                    out = fn(obs, **kw)
                    return out[0] if isinstance(out, tuple) else out
                return actor
            return lambda obs, fn=fn, kw=kw: fn(obs, **kw)
    if callable(policy):
        return policy
    raise TypeError(f"a {type(policy).__name__} is not a policy: it needs predict(obs), act(obs) or to be "
                    "callable, or give a policy file")


def check_action(action: Any, nvec: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(action)
    try:
        flat = a.reshape(-1).astype(np.float64)
    except (TypeError, ValueError):
        flat = None
    if (flat is None or flat.shape != (len(nvec),) or not np.all(np.isfinite(flat))
            or not np.all(flat == np.round(flat)) or np.any(flat < 0) or np.any(flat >= np.asarray(nvec))):
        raise EvaluationError(f"the policy returned the action {np.array2string(a, separator=', ')}; expected "
                              f"{len(nvec)} integers of MultiDiscrete({list(nvec)})")
    return flat.astype(np.int64)


def _obs_size(policy: Any) -> int | None:
    dim = getattr(policy, "obs_dim", None)
    if isinstance(dim, (int, np.integer)):
        return int(dim)
    shape = getattr(getattr(policy, "observation_space", None), "shape", None)
    if isinstance(shape, tuple) and len(shape) == 1:
        return int(shape[0])
    return None


# ------------------------------------------------------------------ cells
def _materialise(spec: tuple, env_config) -> tuple[str, Any]:
    kind, value = spec
    if kind == "path":
        from bimacppo_planner.agent import load_policy

        return POLICY, load_policy(value)
    if kind == "selected":
        from bimacppo_planner.agent import load_policy
        from bimacppo_planner.policy import with_selection

        path, selection, seed = value
        return POLICY, with_selection(load_policy(path), selection, seed)
    if kind == RANDOM:
        return RANDOM, RandomPolicy(env_config.nvec, value)
    return POLICY, value


def _run_cell(job: tuple) -> tuple:
    spec, env_config, map_id, task, n_sv, episodes, mpc_solver, seed_set, mpc_config, slow_svs = job
    from .env import IntersectionEnv

    label, policy = _materialise(spec, env_config)
    actor = as_actor(policy)
    begin = getattr(policy, "begin_episode", None)
    env = IntersectionEnv(map_id=map_id, config=env_config, mpc_solver=mpc_solver, mpc_config=mpc_config,
                          slow_svs=slow_svs)
    nvec = tuple(int(n) for n in env.cfg.nvec)
    counts: Counter = Counter()
    returns = []
    threat = 0
    comfort = Comfort(delta_max=float(env.world.cfg.vehicle.delta_max), dt=float(env.world.dt))
    try:
        for k in range(episodes):
            seed = eval_seed(task, n_sv, k, seed_set)
            obs, _ = env.reset(options={"n_sv": n_sv, "task": task, "scenario_seed": seed})
            if callable(begin):
                begin(seed)
            done = False
            commands, speeds = [], []
            while not done:
                obs, _, term, trunc, info = env.step(check_action(actor(obs), nvec))
                commands.append(info["commands"])
                speeds.append(float(info["x_imr"][2]))
                done = term or trunc
            applied = np.concatenate(commands)
            comfort.add_episode(applied[~np.isnan(applied).any(axis=1)], speeds)   # NaN: ticks after the end
            counts[info["outcome"]] += 1
            threat += int(bool(info.get("threat_entry")))
            returns.append(float(info["episode_return"]))
    finally:
        env.close()
    return label, task, n_sv, counts, returns, comfort, threat, seed_set


def _job_error(job: tuple, exc: BaseException) -> tuple:
    """A failed cell as plain strings (these always cross a process boundary)."""
    if isinstance(exc, CheckpointError):
        return ("checkpoint", exc.path, exc.problem)
    label = "random policy" if job[0][0] == RANDOM else "policy"
    cause = str(exc) if isinstance(exc, EvaluationError) else f"{type(exc).__name__}: {exc}"
    return ("other", f"{label} on {TASKS[job[3]]}, N_sv={job[4]}: {cause}")


def _raise(err: tuple):
    if err[0] == "checkpoint":
        raise CheckpointError(err[1], err[2]) from None
    raise EvaluationError(err[1]) from None


def _worker(tasks, results) -> None:
    """Run cells until the sentinel; report each result or the first failure, then stop."""
    job = None
    try:
        while (item := tasks.get()) is not None:
            i, job = item
            results.put(("ok", i, _run_cell(job)))
    except BaseException as exc:  # noqa: BLE001 - everything goes back to the parent as text
        results.put(("error", -1, _job_error(job, exc) if job is not None else
                     ("other", f"evaluation worker: {type(exc).__name__}: {exc}")))


def _run_parallel(jobs: list[tuple], workers: int, on_result: Callable[[tuple], None]) -> None:
    ctx = mp.get_context("spawn")
    tasks, results = ctx.Queue(), ctx.Queue()
    n = min(workers, len(jobs))
    for i, job in enumerate(jobs):
        tasks.put((i, job))
    for _ in range(n):
        tasks.put(None)
    procs = [ctx.Process(target=_worker, args=(tasks, results), daemon=True) for _ in range(n)]
    for p in procs:
        p.start()
    try:
        pending = len(jobs)
        while pending:
            try:
                kind, _, payload = results.get(timeout=1.0)
            except queue.Empty:
                dead = [p.exitcode for p in procs if p.exitcode not in (None, 0)]
                if dead:
                    raise EvaluationError(f"an evaluation worker died (exit code {dead[0]}) with "
                                          f"{pending} cell(s) unfinished") from None
                if all(p.exitcode is not None for p in procs):   # all gone, queue drained
                    raise EvaluationError(f"the evaluation workers ended with {pending} cell(s) unfinished")
                continue
            if kind == "error":
                _raise(payload)
            pending -= 1
            on_result(payload)
    finally:
        for p in procs:
            if p.is_alive():
                p.terminate()
        for p in procs:
            p.join(timeout=10)
        tasks.close()
        results.close()
        tasks.cancel_join_thread()
        results.cancel_join_thread()


# ------------------------------------------------------------------ the protocol
def default_selection(spec: tuple, loaded: Any) -> str:
    """How ``evaluate`` runs a policy given no ``action_selection``: a file the way it records
    (``Policy.selection``), an object by its own act/predict (argmax where it has a choice)."""
    return getattr(loaded, "selection", "argmax") if spec[0] == "path" else "argmax"


def resolve_policy(policy: Any, env_config=None) -> tuple[tuple, Any, Any]:
    """(worker spec, loaded policy, env config) for what ``evaluate`` was given; a file is
    loaded here (CheckpointError, in this process) and its stored env config is the default."""
    from bimacppo_planner.agent import env_config_of, load_policy, shipped_policy_path
    from bimacppo_planner.decision import EnvConfig
    from bimacppo_planner.policy import Policy

    from .env import as_env_config

    if policy is None or isinstance(policy, (str, os.PathLike)):
        path = shipped_policy_path() if policy is None or str(policy) in ("", "shipped") else Path(policy)
        loaded = load_policy(path)
        spec = ("path", str(path))
    else:
        as_actor(policy)   # TypeError now for what is no policy
        loaded, spec = policy, ("object", policy)
    cfg = as_env_config(env_config)
    if cfg is None:
        cfg = env_config_of(loaded) if isinstance(loaded, Policy) else EnvConfig.load()
    size = _obs_size(loaded)
    if size is not None and size != cfg.obs_dim:
        what = getattr(loaded, "path", None) or type(loaded).__name__
        raise EvaluationError(f"{what}: the policy takes observations of size {size}; the env config gives "
                              f"{cfg.obs_dim} (observation.max_sv={cfg.observation.max_sv})")
    nvec = getattr(loaded, "nvec", None)
    if nvec is not None and tuple(int(x) for x in nvec) != tuple(cfg.nvec):
        what = getattr(loaded, "path", None) or type(loaded).__name__
        raise EvaluationError(f"{what}: the policy acts over nvec={list(nvec)}; the env config gives {list(cfg.nvec)}")
    return spec, loaded, cfg


def resolve_mpc_config(loaded: Any, mpc_config: Any = None):
    """The NMPC config to evaluate ``loaded`` (a resolved policy) with: ``mpc_config`` (an
    MPCConfig or a YAML path) when given, else the one a policy file records, else None (the
    packaged mpc.yaml; a policy that records none was trained before runs recorded theirs)."""
    from bimacppo_mpc import MPCConfig
    from bimacppo_planner.policy import Policy

    from .checkpoint import mpc_config_of

    if isinstance(mpc_config, MPCConfig):
        return mpc_config
    if mpc_config is not None:
        return MPCConfig.load(mpc_config)
    if isinstance(loaded, Policy):
        return mpc_config_of(loaded.meta, loaded.path)
    return None


def check_cells(map_id: str, n_svs: Iterable[int], tasks: Iterable[int]) -> None:
    """Every requested cell exists on the map (ValueError naming the first one that does not)."""
    from bimacppo_sim import load_map

    road = load_map(map_id)
    for n in n_svs:
        if not 0 <= int(n) <= road.max_sv:
            raise ValueError(f"N_sv={n} impossible on map {map_id!r} (0..{road.max_sv})")
    for t in tasks:
        if not 0 <= int(t) < len(TASKS) or TASKS[int(t)] not in road.turns:
            name = TASKS[int(t)] if 0 <= int(t) < len(TASKS) else t
            raise ValueError(f"map {map_id!r} has no task {name!r} (it has {sorted(road.turns)})")


_RANDOM_CACHE: dict[str, CellResult] = {}


def evaluate(policy: Any = None, map_id: str = "dual_lane_4way", n_svs: Iterable[int] = (0, 1, 2, 3),
             tasks: Iterable[int] = (0, 1, 2), episodes: int = 100, workers: int = 2,
             mpc_solver: str = "fast", progress: Callable | None = None, *,
             env_config: Any = None, random_row: bool = True, random_seed: int = 0,
             seed_set: str = "test", mpc_config: Any = None, action_selection: str | None = None,
             sample_seed: int = 0, slow_svs: int = 0) -> list[CellResult]:
    """Run the protocol; see the module docstring.

    ``action_selection`` says how a policy file acts (None: the way the file records,
    ``Policy.selection``, else argmax; an object acts as it does): ``argmax`` per head (deterministic),
    ``median``: each head's weighted median over its ordered values (deterministic,
    ``bimacppo_planner.policy.head_median``), or ``sample``: the trained stochastic policy (``bimacppo_planner.policy.SampledPolicy``), its
    generator seeded per episode from ``(sample_seed, scenario seed)``.

    ``env_config`` (EnvConfig, YAML path or dict) replaces the policy's own (a policy file's
    stored one, else the packaged env.yaml). ``random_row`` adds the random policy's cells
    (``policy == RANDOM``) on the same env config and scenarios; they are cached per process.
    ``mpc_config`` (an MPCConfig, or a YAML overlaying the packaged mpc.yaml) sets the NMPC of
    every cell, so that a policy is evaluated with the controller it was trained with; by default
    that is the one its file records (``mpc_config`` in its run metadata), else the packaged one.
    Objects that cannot be pickled run in this process whatever ``workers`` says (a warning).
    ``slow_svs`` > 0 slows ``draw_n_slow(scenario seed, N_sv, slow_svs)`` SVs per episode (the
    overtaking protocol of paper §IV-C on ``three_lane_straight``; the same draw as training's
    ``--slow-svs``, so a seed gives the same scenario in both). ``progress(cell)`` is called as
    each cell finishes. Returns the policy's cells, then the random ones, each sorted by
    (task, N_sv).
    """
    n_svs, tasks = [int(n) for n in n_svs], [int(t) for t in tasks]
    if seed_set not in SEED_SETS:
        raise ValueError(f"unknown seed set {seed_set!r}; expected one of {sorted(SEED_SETS)}")
    if not 1 <= int(episodes) <= 1000:
        raise ValueError(f"episodes must be in 1..1000 per cell, got {episodes}")
    if int(workers) < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if int(slow_svs) < 0:
        raise ValueError(f"slow_svs must be >= 0, got {slow_svs}")
    check_cells(map_id, n_svs, tasks)
    spec, loaded, cfg = resolve_policy(policy, env_config)
    from bimacppo_planner.policy import ACTION_SELECTIONS
    if action_selection is None:
        action_selection = default_selection(spec, loaded)
    if action_selection not in ACTION_SELECTIONS:
        raise ValueError(f"action_selection must be one of {ACTION_SELECTIONS}, got {action_selection!r}")
    if action_selection != "argmax":
        if spec[0] != "path":
            raise EvaluationError(f"action_selection {action_selection!r} needs a policy file; a policy object "
                                  "acts as it does")
        spec = ("selected", (spec[1], action_selection, int(sample_seed)))
    cells = [(t, n) for t in tasks for n in n_svs]
    mpc_config = resolve_mpc_config(loaded, mpc_config)   # a bad file fails here, once, not in every worker
    mpc_key = None if mpc_config is None else mpc_config.to_dict()
    jobs = [(spec, cfg, map_id, t, n, int(episodes), mpc_solver, seed_set, mpc_config, int(slow_svs)) for t, n in cells]
    results: list[CellResult] = []
    if random_row:
        for t, n in cells:
            key = json.dumps([map_id, cfg.to_dict(), t, n, int(episodes), mpc_solver, int(random_seed), seed_set,
                              mpc_key, int(slow_svs)])
            if key in _RANDOM_CACHE:
                results.append(_RANDOM_CACHE[key])
            else:
                jobs.append(((RANDOM, int(random_seed)), cfg, map_id, t, n, int(episodes), mpc_solver, seed_set,
                             mpc_config, int(slow_svs)))

    def collect(r: tuple) -> None:
        cell = CellResult(r[1], r[2], r[3], r[4], r[0], r[5], r[6], r[7])
        if cell.policy == RANDOM:
            _RANDOM_CACHE[json.dumps([map_id, cfg.to_dict(), cell.task, cell.n_sv, int(episodes), mpc_solver,
                                      int(random_seed), seed_set, mpc_key, int(slow_svs)])] = cell
        results.append(cell)
        if progress:
            progress(cell)

    for cached in list(results):
        if progress:
            progress(cached)
    if workers > 1 and spec[0] == "object":
        try:
            pickle.dumps(spec[1])
        except Exception as exc:  # noqa: BLE001 - any pickling failure means: not across processes
            warnings.warn(f"the policy object cannot be sent to worker processes ({type(exc).__name__}: {exc}); "
                          "evaluating in this process", RuntimeWarning, stacklevel=2)
            workers = 1
    if workers <= 1 or len(jobs) <= 1:
        for job in jobs:
            try:
                r = _run_cell(job)
            except Exception as exc:  # noqa: BLE001 - the same error as a worker's
                err = _job_error(job, exc)
                if err[0] == "checkpoint":
                    raise CheckpointError(err[1], err[2]) from None
                raise EvaluationError(err[1]) from exc
            collect(r)
    else:
        _run_parallel(jobs, int(workers), collect)
    results.sort(key=lambda c: (c.policy != POLICY, c.task, c.n_sv))
    return results


# ------------------------------------------------------------------ tables
def _row(by: Mapping, t: int, n_svs: list[int]) -> list[str]:
    cells = []
    for n in n_svs:
        c = by.get((t, n))
        cells.append("–" if c is None else f"{c.pct('success'):.0f} / {c.pct('collision'):.0f} / {c.pct('timeout'):.0f}")
    return cells


def to_markdown(results: list[CellResult], title: str = "", notes: Iterable[str] = ()) -> str:
    """Table II layout: rows = task, column groups = N_sv, S / C / TO in percent; each task's
    random-policy row (when the results hold one) right under its row. ``notes`` are lines
    under the seed set (e.g. which NMPC ran)."""
    mine = [c for c in results if c.policy != RANDOM]
    rand = {(c.task, c.n_sv): c for c in results if c.policy == RANDOM}
    n_svs = sorted({c.n_sv for c in results})
    by = {(c.task, c.n_sv): c for c in mine}
    head = "| task | " + " | ".join(f"N_sv={n} S / C / TO (%)" for n in n_svs) + " |"
    sep = "|---|" + "---|" * len(n_svs)
    sets = sorted({c.seed_set for c in results})
    lines = ([f"**{title}**", ""] if title else []) + [f"scenario seeds: {' + '.join(sets)} set",
                                                        *notes, "", head, sep]
    for t in sorted({c.task for c in results}):
        if any(k[0] == t for k in by) or not rand:
            lines.append(f"| {TASKS[t]} | " + " | ".join(_row(by, t, n_svs)) + " |")
        if any(k[0] == t for k in rand):
            lines.append(f"| {TASKS[t]}, random policy | " + " | ".join(_row(rand, t, n_svs)) + " |")
    if rand:
        lines += ["", "random policy: uniform random actions on the same scenario seeds (the floor)."]
    tasks = sorted({c.task for c in mine})

    def cell_table(caption: str, column: str, text: Callable[[CellResult], str | None]) -> list[str]:
        """One more table over the policy's cells: a caption, one column per N_sv, ``text(cell)``
        in each (None, or no cell there: '–')."""
        out = ["", caption, "", "| task | " + " | ".join(f"N_sv={n}{column}" for n in n_svs) + " |", sep]
        for t in tasks:
            row = [None if by.get((t, n)) is None else text(by[(t, n)]) for n in n_svs]
            out.append(f"| {TASKS[t]} | " + " | ".join("–" if x is None else x for x in row) + " |")
        return out

    def interval(c: CellResult) -> str | None:
        if c.n == 0:
            return None
        lo, hi = c.success_interval()
        # the success to the interval's precision: rounded to a whole percent, 99.6 of 500 would
        # read 100 beside an interval that ends below it
        return f"{c.pct('success'):.1f} [{lo:.1f}, {hi:.1f}] of {c.n}"

    def comfort(c: CellResult) -> str | None:
        q = c.comfort
        if q is None or not q.ticks:
            return None
        return f"{q.full_lock_pct:.1f} / {q.reversal_pct:.1f} / {q.rms_jerk:.1f} / {q.alternation_pct:.1f}"

    if by:
        lines += cell_table(f"Success (%) with its {100 * CI_LEVEL:.0f} % Wilson score interval (the policy's cells)",
                            " success [interval]", interval)
    if any(c.comfort is not None and c.comfort.ticks for c in mine):
        lines += cell_table("Ride comfort (the policy's cells): ticks at full steering lock (%) / lock-to-lock "
                            "reversals between consecutive ticks (%) / RMS jerk (m/s³) / go-stop alternations "
                            "between consecutive decisions (%)", " lock / rev. / jerk / alt.", comfort)
    if any(c.n_sv > 0 for c in mine):
        lines += cell_table("Entered the junction while the scripted yield rule's threat test held (% of the "
                            "policy's episodes; measured on the true SV states)", "",
                            lambda c: f"{100.0 * c.threat_entries / max(c.n, 1):.0f}")
    return "\n".join(lines) + "\n"


def to_csv(results: list[CellResult]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(["task", "n_sv", "episodes", "success_pct", "collision_pct", "timeout_pct", "mean_return",
                "full_lock_pct", "lock_reversal_pct", "rms_jerk", "go_stop_alternation_pct", "threat_entry_pct",
                "seed_set", "success_ci_low", "success_ci_high"])
    for c in results:
        q = c.comfort
        ride = ["nan"] * 4 if q is None or not q.ticks else \
            [f"{q.full_lock_pct:.2f}", f"{q.reversal_pct:.2f}", f"{q.rms_jerk:.3f}", f"{q.alternation_pct:.2f}"]
        w.writerow([TASKS[c.task], c.n_sv, c.n, f"{c.pct('success'):.1f}", f"{c.pct('collision'):.1f}",
                    f"{c.pct('timeout'):.1f}", f"{np.mean(c.returns) if c.returns else float('nan'):.3f}", *ride,
                    f"{100.0 * c.threat_entries / max(c.n, 1):.1f}", c.seed_set,
                    *(f"{v:.2f}" for v in c.success_interval())])
    return buf.getvalue()


def write_outputs(results: list[CellResult], out_prefix: str | Path, title: str = "",
                  notes: Iterable[str] = ()) -> tuple[Path, Path]:
    """OUT.md (the table, random rows included) and OUT.csv (the policy's cells, one row per
    cell); the random policy's cells, if any, go to OUT_random.csv in the same layout."""
    out_prefix = Path(out_prefix)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    md, cs = out_prefix.with_suffix(".md"), out_prefix.with_suffix(".csv")
    md.write_text(to_markdown(results, title, notes))
    cs.write_text(to_csv([c for c in results if c.policy != RANDOM]))
    rand = [c for c in results if c.policy == RANDOM]
    if rand:
        out_prefix.with_name(out_prefix.name + "_random").with_suffix(".csv").write_text(to_csv(rand))
    return md, cs
