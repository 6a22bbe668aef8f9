"""Run one contestant in its own process and read its ``RESULT {json}`` line (the peers' benchmarks share it)."""

from __future__ import annotations

import json
import os
import subprocess
import time


def run_child(python: str, code: str, args: dict, extra_env: dict | None = None) -> dict:
    """``python -c code json(args)`` with single-threaded BLAS; its result with the process's ``wall`` time (s)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", **(extra_env or {})}
    t0 = time.perf_counter()
    p = subprocess.run([python, "-c", code, json.dumps(args)], capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return {**json.loads(line[7:]), "wall": wall}
    raise RuntimeError(f"child failed ({p.returncode}):\n{p.stderr[-3000:]}")
