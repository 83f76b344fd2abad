"""What a run made, said at its end (or on Ctrl-C): success rates, time, its folder, and the commands that use it."""

from __future__ import annotations

import math
import shlex
from collections.abc import Sequence
from pathlib import Path


def _duration(seconds: float) -> str:
    minutes, seconds = divmod(int(round(seconds)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min" if hours else f"{minutes} min {seconds:02d} s"


def summary(history: Sequence[dict], run_dir: Path, seconds: float, *, threshold: float = 0.9,
            overrides: Sequence[str] = (), interrupted: bool = False, saved_at: int | None = None,
            resumed_at: int = 0) -> str:
    """The lines printed when a run ends.

    Args:
        history: the run's metrics rows (evaluated ones carry ``success_rate``).
        run_dir: the run folder.
        seconds: wall-clock seconds this process trained.
        threshold: the success rate whose first crossing is reported (``train.stop_success``, else 0.9).
        overrides: the command line's overrides, repeated in the resume command.
        interrupted: the run was stopped by Ctrl-C (``saved_at``: the iterations its last checkpoint holds).
        resumed_at: the iterations the run held when this process took it up (a resumed run).

    >>> rows = [{"iteration": i, "success_rate": r} for i, r in enumerate([0.1, 0.92, 0.88])]
    >>> print(summary(rows, Path("out/run"), 95, overrides=["env=reach"]).splitlines()[1])
    success rate: final 0.88, best 0.92 (iteration 1), first >= 0.9 at iteration 1
    """
    evaluated = [row for row in history if not math.isnan(row.get("success_rate", math.nan))]
    iterations = len(history)
    done = (f"iterations {resumed_at}–{iterations - 1} ({iterations} in all)" if resumed_at
            else f"{iterations} iterations")
    if interrupted:
        head = f"interrupted after {done} in {_duration(seconds)}; its last checkpoint holds {saved_at} iterations"
    else:
        head = f"trained {done} in {_duration(seconds)}"
    lines = [head]
    if evaluated:
        best = max(evaluated, key=lambda row: row["success_rate"])
        first = next((row["iteration"] for row in evaluated if row["success_rate"] >= threshold), None)
        reached = f"first >= {threshold:g} at iteration {first}" if first is not None else f"never >= {threshold:g}"
        lines.append(f"success rate: final {evaluated[-1]['success_rate']:.2f}, best {best['success_rate']:.2f} "
                     f"(iteration {best['iteration']}), {reached}")
    folder = shlex.quote(str(run_dir))
    dropped = ("resume=", "hydra.run.dir=") + (() if interrupted else ("train.iterations=",))
    resume = " ".join(shlex.quote(o) for o in overrides if not o.startswith(dropped))
    lines += [
        f"run folder: {run_dir} (metrics.csv, checkpoint.pt, policy.pt, config.yaml)",
        f"  plot:     python -m gchgg.analysis.plot {folder} --out {shlex.quote(str(run_dir / 'curves.png'))}",
        f"  evaluate: python -m gchgg.analysis.evaluate {folder} --episodes 100",
        f"  export:   python -m gchgg.analysis.export {folder} --format onnx "
        f"--out {shlex.quote(str(run_dir / 'policy.onnx'))}",
        f"  resume:   python -m gchgg.train {resume + ' ' if resume else ''}resume=true hydra.run.dir={folder}"
        + ("" if interrupted else " train.iterations=<more>"),
    ]
    return "\n".join(lines)
