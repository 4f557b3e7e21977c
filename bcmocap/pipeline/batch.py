"""``bcmocap batch CAPTURE... --out DIR``: many captures through ``bcmocap run``, on one cluster.

Each capture's run goes to ``DIR/<capture folder name>/`` (``-2``, ``-3`` … appended when names repeat) and
is resumable there as any run. With ``--cluster`` every capture's run is one task whose own pieces of
work (cameras, chunks, windows) are tasks on the same cluster (the task leaves its worker slot while it
waits for them), so captures and their pieces share the workers; without one the captures run one after
the other in this process. One failed capture does not stop the others: the summary table
(``DIR/batch.json`` and printed) gives per capture the registered fractions, the errors against the
ground truth when the capture has one, the time, and the failure's reason.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from collections.abc import Callable
from pathlib import Path

from ..atomic import write_json_atomic
from ..compilation_cache import release_compiled_programs


@dataclasses.dataclass(frozen=True)
class BatchItem:
    """One capture of a batch and where its run goes."""

    capture: Path
    out: Path


def batch_items(captures: list[str | Path], out: str | Path) -> list[BatchItem]:
    """Each capture with its own run folder under ``out`` (named after the capture folder, made unique).

    Raises:
        ValueError: no captures, or a capture given twice.
    """
    if not captures:
        raise ValueError("batch: no capture folders given")
    seen, items, taken = set(), [], set()
    for capture in captures:
        capture = Path(capture)
        real = capture.resolve()
        if real in seen:
            raise ValueError(f"{capture}: given twice")
        seen.add(real)
        base = real.name or "capture"
        name, k = base, 1
        while name in taken:
            k += 1
            name = f"{base}-{k}"
        taken.add(name)
        items.append(BatchItem(capture, Path(out) / name))
    return items


def run_one(item: BatchItem, config_dict: dict, executor=None, stop_after: str | None = None) -> dict:
    """Run (or resume) one capture (up to ``stop_after``); its summary row (never raises for a failed capture:
    the row says why)."""
    from ..io.messages import one_line_error
    from .config import RunConfig
    from .run import run_pipeline

    clock = time.perf_counter()
    row = {"capture": str(item.capture), "out": str(item.out), "ok": False}
    try:
        with contextlib.ExitStack() as stack:
            if executor is None:  # a task on a cluster: its pieces become tasks of the same cluster
                from distributed import worker_client

                from .cluster import Executor

                executor = Executor(stack.enter_context(worker_client()))
            log = run_pipeline(item.capture, item.out, RunConfig.from_dict(config_dict), executor=executor,
                               log=lambda line: None, stop_after=stop_after)
        row.update(_summary(item.out, log))
        row["ok"] = True
    except (ValueError, OSError, MemoryError, FloatingPointError) as exc:
        row["error"] = one_line_error(exc)
    except Exception as exc:  # an unexpected failure of one capture is reported, not raised, in a batch
        row["error"] = f"{type(exc).__name__}: {one_line_error(exc)}"
    row["seconds"] = round(time.perf_counter() - clock, 1)
    release_compiled_programs()  # many captures in one process would run out of memory mappings
    return row


def _summary(out: Path, log: dict) -> dict:
    """The registered fractions of the run log and the solved errors of ``metrics.json`` (when written)."""
    front = log.get("stages", {}).get("frontend", {})
    row = {f"registered_{trial}": front.get(trial, {}).get("registered_fraction") for trial in ("rom", "capture")}
    try:
        solved = json.loads((out / "metrics.json").read_text())["solved"]
        row["joint_position_error_cm"] = solved["joint_position_error_cm"]["mean"]
        row["joint_angle_error_deg"] = solved["joint_angle_error_deg"]["mean"]
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return row


def run_batch(captures: list[str | Path], out: str | Path, config, executor,
              log: Callable[[str], None] = print, stop_after: str | None = None) -> list[dict]:
    """Run every capture (on ``executor``'s cluster as one task each, else one after the other; each up to
    ``stop_after``) and write ``out/batch.json``; returns the rows in the order given."""
    items = batch_items(captures, out)
    Path(out).mkdir(parents=True, exist_ok=True)
    config_dict = config.to_dict()
    rows: list[dict | None] = [None] * len(items)
    clock = time.perf_counter()

    def done(i: int, row: dict) -> None:
        rows[i] = row
        finished = sum(r is not None for r in rows)
        state = "done" if row["ok"] else f"FAILED: {row['error']}"
        log(f"[{finished}/{len(items)}] {items[i].capture}: {state} ({row['seconds']:.0f} s)")
        write_json_atomic(Path(out) / "batch.json", {"rows": [r for r in rows if r is not None],
                                                     "seconds": round(time.perf_counter() - clock, 1)})

    if executor.distributed:
        executor.map(_BatchTask(config_dict, stop_after), items, label="capture", on_done=done)
    else:
        for i, item in enumerate(items):
            log(f"{item.capture} → {item.out} ...")
            done(i, run_one(item, config_dict, executor, stop_after))
    write_json_atomic(Path(out) / "batch.json", {"rows": rows, "seconds": round(time.perf_counter() - clock, 1)})
    return rows


@dataclasses.dataclass(frozen=True)
class _BatchTask:
    """``run_one`` of an item as a cluster task (picklable: the settings only)."""

    config_dict: dict
    stop_after: str | None = None

    def __call__(self, item: BatchItem) -> dict:
        return run_one(item, self.config_dict, stop_after=self.stop_after)


def summary_table(rows: list[dict]) -> str:
    """The rows as a fixed-width table."""
    def cell(value, fmt: str) -> str:
        return "–" if value is None else format(value, fmt)

    lines = [f"{'capture':<28}{'ROM reg.':>10}{'capture reg.':>14}{'joints cm':>11}{'angles °':>10}{'seconds':>9}  result"]
    for r in rows:
        name = Path(r["capture"]).name[:27]
        lines.append(f"{name:<28}{cell(r.get('registered_rom'), '.1%'):>10}{cell(r.get('registered_capture'), '.1%'):>14}"
                     f"{cell(r.get('joint_position_error_cm'), '.2f'):>11}{cell(r.get('joint_angle_error_deg'), '.2f'):>10}"
                     f"{r['seconds']:>9.0f}  {'ok' if r['ok'] else r['error']}")
    return "\n".join(lines)
