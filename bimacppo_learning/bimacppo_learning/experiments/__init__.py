"""``bimacppo-experiments``: the paper's experiment grid, from training to the results page.

Every method x seed is a ``bimacppo-train`` run (a Ray task: local Ray, or a cluster with
``--address``) in ``<runs_dir>/<map>/<method>-s<seed>``;
``evaluate`` caches each run's protocol CSVs next to it; ``overtake`` fine-tunes the best
BiM-ACPPO seed on the three-lane road; ``report`` turns whatever exists into
``docs/results_experiments.md`` and says what is missing instead of inventing numbers.
Each step skips what is already done, so ``all`` can be re-run after any interruption.
docs/experiments.md says how to run it and why each constant is what it is.

Modules, one job each: ``config`` (experiments.yaml on bimacppo_common.config: the sections,
their checks, where outputs live), ``runs`` (what is on disk and still valid),
``pool`` (Ray: one task per run, progress, failures), ``train`` / ``evaluation`` /
``overtake`` (the steps), ``traffic`` (the overtaking env), ``stats`` (means, spreads,
curves), ``results`` (the markdown page and figures), ``cli``.
This package namespace re-exports their public names.
"""
from bimacppo_common.config import ConfigError  # noqa: F401
from .config import (CONFIG_PATH, CURRICULA, DRIVERS, MAPS, METHOD_NAMES, EvalSection,  # noqa: F401
                     ExperimentConfig, ExperimentError, OvertakeSection, ReportSection, TrainSection,
                     check_methods, load_experiment_config)
from .runs import (RunStatus, eval_is_fresh, has_checkpoint, last_episode, protocol_cells,  # noqa: F401
                   read_eval_csv, read_history, run_settings, run_status, settings_mismatch)
from .pool import Cluster, Job, Outcome, RunFailed  # noqa: F401
from .traffic import draw_n_slow, make_overtake_env  # noqa: F401
from .stats import aggregate_cells, episodes_to_fraction, mean_counts, mean_std_curve, rolling_rate  # noqa: F401
from .train import train, train_argv  # noqa: F401
from .evaluation import evaluate_all, evaluate_reference  # noqa: F401
from .overtake import best_source_seed, overtake, overtake_test, test_is_fresh  # noqa: F401
from .results import counts_markdown, report, table_markdown  # noqa: F401
from .cli import build_parser, main  # noqa: F401
