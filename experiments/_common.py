"""Shared helpers for the benchmark scripts in `experiments/`.

Each benchmark measures one case per fresh subprocess (a *worker*), so that the peak
resident memory of a case is that process's own high-water mark and one case's caches,
compiled code or leaks cannot flatter the next. This module holds the pieces every
benchmark needs: timing, memory, running workers, machine information, and writing
JSON, markdown and charts.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

# One JAX CPU device per core in every experiment (read when JAX starts, so this module is
# imported first): `jaxvox.trace` shards concrete rays over the devices. A script that
# measures device counts sets its own (bench_trace ``--devices``, distributed_build).
os.environ.setdefault("JAX_NUM_CPU_DEVICES", str(os.cpu_count() or 1))

# Every experiment (and its workers, which inherit the environment) runs with glibc's
# malloc asking for transparent huge pages, as the `jaxvox` command does: see
# `jaxvox.cli.ask_for_huge_pages` (the script starts again once, before any work). A
# worker started by `run_worker(..., plain=True)` does not: it measures what a plain
# `python` process or a notebook gets.
from jaxvox.cli import HUGE_PAGES, ask_for_huge_pages  # noqa: E402

if os.environ.get("JAXVOX_BENCH_PLAIN") != "1":
    ask_for_huge_pages()

REPO_ROOT = Path(__file__).resolve().parent.parent
MESH_DIR = REPO_ROOT.parent / "shared" / "meshes"
RESULTS_DIR = REPO_ROOT / "experiments" / "results"


COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_compiled: list[float] | None = None


def compile_count() -> int:
    """XLA compilations in this process so far (counted from the first call on, through
    `jax.monitoring`; call it once before the work to count)."""
    global _compiled
    if _compiled is None:
        import jax

        _compiled = []
        jax.monitoring.register_event_duration_secs_listener(
            lambda name, secs, **kw: _compiled.append(secs) if name == COMPILE_EVENT else None
        )
    return len(_compiled)


def time_calls(fn: Callable[[], Any], repeats: int) -> tuple[dict, Any]:
    """Times a warm-up call and then `repeats` further calls of `fn`.

    `fn` must return only once its work is done (for JAX, it should call
    `jax.block_until_ready` on its result).

    Returns:
      (timing, result): timing holds `first_s` (the warm-up call, which includes any
      compilation), `times_s` (the repeats), `median_s`, `compile_s` = first call
      minus median (clipped at 0), and `compiles_first` and `compiles_warm`, the XLA
      compilations in the first call and in the repeats (`compile_count`); result is
      the last call's return value.
    """
    compiled = compile_count()
    start = time.perf_counter()
    result = fn()
    first = time.perf_counter() - start
    compiles_first, compiled = compile_count() - compiled, compile_count()
    times = []
    for _ in range(repeats):
        result = None  # free the previous result first: peak memory is one call's
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    median = statistics.median(times) if times else first
    timing = dict(
        first_s=first,
        times_s=times,
        median_s=median,
        compile_s=max(first - median, 0.0),
        compiles_first=compiles_first,
        compiles_warm=compile_count() - compiled,
    )
    return timing, result


def peak_rss_mib() -> float:
    """This process's resident-memory high-water mark so far, in MiB.

    Reads VmHWM from /proc/self/status: unlike ``ru_maxrss``, which Linux carries over
    from the parent through fork and exec (so every worker would report at least the
    parent's peak), it belongs to this process's own address space.
    """
    try:
        with open("/proc/self/status") as status:
            for line in status:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def environment() -> str:
    """How this process was started: ``"plain"`` (no special environment, as a user's
    `python` or notebook) or ``"huge pages"`` (``GLIBC_TUNABLES`` asking for them)."""
    return "huge pages" if HUGE_PAGES in os.environ.get("GLIBC_TUNABLES", "") else "plain"


def run_worker(script: str | Path, spec: dict, *, timeout: float, plain: bool = False) -> dict:
    """Runs `python script --worker '<spec as JSON>'` in a fresh process and returns its result.
    With `plain`, the worker starts without the huge-page setting (`environment`).

    The worker must print its result as one JSON object on the last line of stdout; its
    stderr goes straight to ours. A crash, a kill (e.g. out of memory) or a timeout is
    returned as ``{"error": "..."}`` so that one failed case does not end a long sweep.
    """
    cmd = [sys.executable, str(script), "--worker", json.dumps(spec)]
    env = dict(os.environ)
    if plain:
        tunables = [t for t in env.pop("GLIBC_TUNABLES", "").split(":") if t and t != HUGE_PAGES]
        env.update(JAXVOX_BENCH_PLAIN="1", **({"GLIBC_TUNABLES": ":".join(tunables)} if tunables else {}))
    try:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {timeout:.0f} s"}
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        return {"error": f"worker exited with status {proc.returncode}"}
    return json.loads(lines[-1])


def experiment_parser(doc: str | None):
    """An argument parser with the options every sweep shares: ``--worker`` (internal),
    ``--smoke``, ``--resolutions`` (None: the script's default), ``--timeout`` per case in
    seconds (3600) and ``--out`` (the results folder)."""
    import argparse

    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--smoke", action="store_true", help="small sizes, *_smoke outputs")
    parser.add_argument("--resolutions", type=int, nargs="*", default=None)
    parser.add_argument("--timeout", type=float, default=3600, help="seconds per case")
    parser.add_argument("--out", type=Path, default=RESULTS_DIR)
    return parser


def answer_as_worker(args, worker: Callable[[dict], dict]) -> bool:
    """When the script runs as a worker (``--worker '<spec>'``), prints `worker(spec)` as
    the JSON line `run_worker` reads and returns True; otherwise returns False."""
    if not args.worker:
        return False
    print(json.dumps(worker(json.loads(args.worker))))
    return True


def package_versions(names: Iterable[str]) -> dict[str, str | None]:
    """Installed versions of the given distributions (None where one is missing), without importing them."""
    versions = {}
    for name in names:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions


def machine_info(packages: Iterable[str] = ()) -> dict:
    """The host a benchmark ran on: CPU model and count, memory, OS, Python and package versions."""
    cpu_model = platform.processor()
    try:
        with open("/proc/cpuinfo") as f:
            cpu_model = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return dict(
        cpu_model=cpu_model,
        cpu_count=os.cpu_count(),
        cpus_available=len(os.sched_getaffinity(0)),
        memory_gib=os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30,
        platform=platform.platform(),
        python=platform.python_version(),
        packages=package_versions(packages),
    )


def write_json(path: Path, data: Any) -> None:
    """Writes `data` as indented JSON, creating the parent folder."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=2) + "\n")


def markdown_table(rows: Sequence[dict], columns: Sequence[tuple[str, str]]) -> str:
    """A GitHub markdown table; `columns` lists (key in each row, header), missing keys print '-'."""
    header = "| " + " | ".join(title for _, title in columns) + " |"
    rule = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(str(row.get(key, "-")) for key, _ in columns) + " |" for row in rows]
    return "\n".join([header, rule, *body]) + "\n"


def case_rows(cases: Sequence[dict], rows_of: Callable[[dict], list[dict]]) -> list[dict]:
    """Table rows of every case: `rows_of(case)`, or one row naming a failed case's error."""
    out = []
    for case in cases:
        if "error" in case:
            out.append(dict(mesh=case["mesh"], R=case["resolution"], method=case["error"]))
        else:
            out += rows_of(case)
    return out


def new_figure(ncols: int, *, rows: int = 1, width: float = 6.0, height: float = 4.5):
    """A matplotlib figure with `rows` x `ncols` axes (each `width` x `height` inches),
    drawn off-screen (Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(rows, ncols, figsize=(width * ncols, height * rows), constrained_layout=True)


def save_figure(fig, path: Path) -> None:
    """Saves `fig` as a PNG and closes it."""
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def progress(iterable: Iterable, **kwargs):
    """A tqdm progress bar that switches itself off when stderr is not a terminal."""
    from tqdm import tqdm

    return tqdm(iterable, disable=None, **kwargs)
