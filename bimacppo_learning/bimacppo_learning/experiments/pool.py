"""Runs the grid's jobs as Ray tasks: a local Ray by default, an existing cluster with an address.

Each job is one task that declares its CPUs; Ray runs as many at once as the cluster's CPUs
allow and queues the rest. A task runs in a fresh worker process (``max_calls=1``: nothing a
run leaves in its process, such as torch threads, logging handlers or env subprocesses, reaches
the next), in the driver's working directory when that exists on the node, with its stdout and
stderr (file descriptors, so child processes too) appended to the job's log file. A job that
raises is reported as one line naming its log, and the other jobs go on; the caller counts the
failures and decides the exit code.
"""
from __future__ import annotations

import os
import socket
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

from .config import ExperimentError


class RunFailed(Exception):
    """A job's own verdict that it did not produce its outputs (the message is what is reported)."""


@dataclass(frozen=True)
class Job:
    name: str                      # e.g. "bimab-s0", "bimab-s0 on single_lane_4way"
    fn: Callable[..., str]         # module-level (importable on every node); returns a one-line summary
    kwargs: Mapping[str, Any]
    log: Path
    num_cpus: int


@dataclass(frozen=True)
class Outcome:
    name: str
    ok: bool
    message: str                   # the job's summary, or its error on one line
    log: Path


def one_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    if isinstance(exc, RunFailed):
        return text[0] if text else "failed"
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__


def execute(fn: Callable[..., str], kwargs: Mapping[str, Any], log: str, num_cpus: int, name: str,
            cwd: str, events) -> tuple[bool, str]:
    """The body of every Ray task (runs in the worker): (True, summary) or (False, error line)."""
    import torch

    torch.set_num_threads(max(1, int(num_cpus)))
    if events is not None:
        # fire and forget: a task blocked in ray.get (Queue.put waits on the queue actor) lends
        # its CPUs back to the scheduler, which then starts another task on them
        events.actor.put_nowait.remote(name)
    log_path = Path(log)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    old_cwd = os.getcwd()
    with log_path.open("a", buffering=1) as fh:
        os.dup2(fh.fileno(), 1)
        os.dup2(fh.fileno(), 2)
        try:
            if os.path.isdir(cwd):
                os.chdir(cwd)
            print(f"== {name}: {time.strftime('%Y-%m-%d %H:%M:%S')} on {socket.gethostname()}, pid {os.getpid()}, "
                  f"{num_cpus} CPU(s)", flush=True)
            return True, fn(**kwargs)
        except (Exception, SystemExit) as exc:
            if isinstance(exc, RunFailed):
                print(f"FAILED: {exc}", flush=True)
            else:
                traceback.print_exc()
            return False, one_line(exc)
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
            os.chdir(old_cwd)


class Cluster:
    """The Ray this command uses, connected on the first job (a step with nothing to do never
    starts Ray). An already initialised Ray (a test, a notebook) is used as it is and left
    running; one this object started or connected is shut down by ``close``."""

    def __init__(self, address: str | None = None, num_cpus: int | None = None):
        self.address = address
        self.num_cpus = num_cpus
        self._owned = False

    def connect(self) -> None:
        import ray

        if ray.is_initialized():
            return
        if self.address is None:
            ray.init(num_cpus=self.num_cpus, include_dashboard=False, log_to_driver=False)
        else:
            if self.num_cpus is not None:
                raise ExperimentError("--num-cpus sizes a local Ray; a cluster's CPUs are those its nodes "
                                      "offered at `ray start` (--num-cpus there)")
            try:
                ray.init(address=self.address, log_to_driver=False)
            except ConnectionError as exc:
                raise ExperimentError(f"cannot connect to the Ray cluster at {self.address!r}: {exc}") from None
        self._owned = True

    def close(self) -> None:
        if self._owned:
            import ray

            ray.shutdown()
            self._owned = False

    def run(self, jobs: list[Job], desc: str, echo: Callable[[str], None] | None = None,
            poll_s: float = 2.0) -> list[Outcome]:
        """Run ``jobs`` to the end, showing done / running / queued / failed; one line per
        finished job (its summary, or FAILED with the error and the log path)."""
        if not jobs:
            return []
        import ray
        from ray.util.queue import Empty, Queue
        from tqdm.auto import tqdm

        self.connect()
        cpus = ray.cluster_resources().get("CPU", 0.0)
        for j in jobs:
            if j.num_cpus > cpus:
                raise ExperimentError(f"job {j.name} asks for {j.num_cpus} CPUs but the Ray cluster has {cpus:g}: "
                                      "lower train.num_cpus / evaluation.num_cpus or add nodes")
        events = Queue(actor_options={"num_cpus": 0})
        task = ray.remote(max_calls=1)(execute)
        refs = {}
        for j in jobs:
            ref = task.options(num_cpus=j.num_cpus, name=j.name).remote(
                j.fn, dict(j.kwargs), str(j.log), j.num_cpus, j.name, os.getcwd(), events)
            refs[ref] = j
        bar = tqdm(total=len(jobs), unit="run", desc=desc, disable=None)
        say = echo or bar.write
        running: set[str] = set()
        outcomes: list[Outcome] = []
        last = None

        def show():
            nonlocal last
            n_fail = sum(not o.ok for o in outcomes)
            counts = (len(outcomes) - n_fail, len(running), len(jobs) - len(outcomes) - len(running), n_fail)
            if counts == last:
                return
            last = counts
            line = "done {}, running {}, queued {}, failed {}".format(*counts)
            bar.set_postfix_str(line)
            if bar.disable:
                say(f"{desc}: {line} (of {len(jobs)})")

        pending = list(refs)
        try:
            while pending:
                ready, pending = ray.wait(pending, num_returns=1, timeout=poll_s)
                while True:
                    try:
                        running.add(events.get_nowait())
                    except Empty:
                        break
                for ref in ready:
                    j = refs[ref]
                    try:
                        ok, msg = ray.get(ref)
                    except ray.exceptions.RayError as exc:   # the worker died, or the node went away
                        ok, msg = False, one_line(exc)
                    running.discard(j.name)
                    outcomes.append(Outcome(j.name, ok, msg, j.log))
                    say(f"{j.name}: {msg}" if ok else f"{j.name}: FAILED: {msg} (log: {j.log})")
                    bar.update(1)
                show()
        except KeyboardInterrupt:
            for ref in pending:
                ray.cancel(ref, force=True)
            raise
        finally:
            bar.close()
            ray.kill(events.actor)
        return outcomes
