"""OpenMP's wait policy: idas_sumo makes idle threads sleep, and says when it comes too late for that."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


def _import(order: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    code = f"import warnings; warnings.simplefilter('error'); {order}; print(os.environ['OMP_WAIT_POLICY'])"
    return subprocess.run(
        [sys.executable, "-c", f"import os; {code}"], env=env, capture_output=True, text=True, check=False
    )


def test_idas_sumo_first_sets_passive_threads_quietly() -> None:
    done = _import("import idas_sumo, torch")
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "PASSIVE"


def test_torch_first_is_a_warning_naming_the_fix() -> None:
    done = _import("import torch, idas_sumo")
    assert done.returncode != 0
    assert "RuntimeWarning" in done.stderr and "import idas_sumo first" in done.stderr


@pytest.mark.parametrize("policy", ["ACTIVE", "PASSIVE"])
def test_a_users_own_policy_wins_and_is_not_warned_about(policy: str) -> None:
    env = {**os.environ, "OMP_WAIT_POLICY": policy}
    code = "import warnings; warnings.simplefilter('error'); import torch, idas_sumo, os; print(os.environ['OMP_WAIT_POLICY'])"
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == policy
