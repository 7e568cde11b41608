"""The reference checks marked ``codegen`` again, compiled as users' programs are.

The suite compiles with XLA's loop emitters and LLVM's level 1 optimizations, which
compile faster (`tests/conftest.py`'s ``SUITE_FLAGS``); users' programs are compiled by
XLA's default fusion emitters at level 2. This runs the tests marked
``codegen`` (traversal against brute force, voxelization against its reference, closest
points and signs against float64, sphere tracing against analytic hits, exact distances,
sparse fields) in a pytest of their own with XLA's defaults; when this test is
collected, the marked tests run only there (`tests/conftest.py`).
"""

from __future__ import annotations

import os
import subprocess
import sys

from tests.conftest import CODEGEN_FILES, DEFAULT_EMITTERS, REPO_ROOT, SUITE_FLAGS


def test_reference_checks_pass_with_the_default_emitters():
    if DEFAULT_EMITTERS:  # (this is the inner run)
        return
    flags = " ".join(flag for flag in os.environ.get("XLA_FLAGS", "").split() if flag not in SUITE_FLAGS)
    env = dict(os.environ, JAXVOX_TEST_EMITTERS="default", XLA_FLAGS=flags)
    files = CODEGEN_FILES or ["tests"]  # the modules of the marked tests (when collected beside this one)
    command = [sys.executable, "-m", "pytest", "-q", "-n", "0", "-m", "codegen", "-p", "no:cacheprovider", *files]
    run = subprocess.run(command, cwd=REPO_ROOT, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
    assert " passed" in run.stdout and " failed" not in run.stdout, run.stdout[-2000:]
