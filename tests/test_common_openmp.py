"""The OpenMP wait policy is set before either OpenMP runtime of a training process loads."""
import os
import subprocess
import sys

import pytest

# Records OMP_WAIT_POLICY at the moment torch starts importing, then imports the module under test.
PROBE = """
import importlib, os, sys
seen = []
class Probe:
    def find_spec(self, name, path=None, target=None):
        if name == "torch" and not seen:
            seen.append(os.environ.get("OMP_WAIT_POLICY"))
        return None
sys.meta_path.insert(0, Probe())
importlib.import_module(sys.argv[1])
import torch  # the module may load it lazily
print(seen[0])
"""


@pytest.mark.parametrize("module", ["bimacppo_learning.trainer", "bimacppo_learning.ppo",
                                    "bimacppo_planner.policy"])
def test_torch_loads_with_passive_openmp_threads_whichever_module_imports_it_first(module):
    """Torch reads OMP_WAIT_POLICY once, at import: a module of ours that imports torch before
    anything else must still have set the policy (spinning idle threads make runs that share the
    cores several times slower); a policy the user set is kept."""
    base = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    for env, want in ((base, "PASSIVE"), ({**base, "OMP_WAIT_POLICY": "ACTIVE"}, "ACTIVE")):
        out = subprocess.run([sys.executable, "-c", PROBE, module], env=env, capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 0, out.stderr[-2000:]
        assert out.stdout.split()[-1] == want
