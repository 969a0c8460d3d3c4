"""Progress of long solves: the solvers report their iterations here, and nothing happens unless a caller listens.

    from nrsfm.progress import listen
    with listen(lambda p: print(p.solver, p.stage, p.step, p.values)):
        rec = nrsfm.solve(seq, "empnd")

``nrsfm solve`` listens with a progress bar on stderr when stderr is a
terminal (``--progress always|never`` overrides that). The listener lives in a context
variable: it sees the reports of the thread (and asyncio task) that installed
it, not those of worker threads or processes, and costs one lookup per report
when nobody listens.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
from collections.abc import Callable, Iterator


@dataclasses.dataclass(frozen=True)
class Progress:
    """One report: ``solver`` (registry name), ``stage`` (e.g. ``"EM"``, ``"camera rounds"``), ``step`` (1-based
    count within the stage), ``total`` (the stage's cap, or None when unknown) and named ``values`` (cost,
    RMSE, ...)."""

    solver: str
    stage: str
    step: int
    total: int | None
    values: dict[str, float]


_LISTENER: contextvars.ContextVar[Callable[[Progress], None] | None] = contextvars.ContextVar(
    "nrsfm_progress_listener", default=None)


def report(solver: str, stage: str, step: int, total: int | None = None, **values: float) -> None:
    """Tell the listener, if any, that ``solver`` reached ``step`` of ``stage``."""
    listener = _LISTENER.get()
    if listener is not None:
        listener(Progress(solver, stage, int(step), None if total is None else int(total),
                          {k: float(v) for k, v in values.items()}))


def current() -> Callable[[Progress], None] | None:
    """The listener of this context (None when nobody listens): to hand to a worker thread's :func:`listen`."""
    return _LISTENER.get()


@contextlib.contextmanager
def listen(callback: Callable[[Progress], None] | None) -> Iterator[None]:
    """Send every :func:`report` made in this context to ``callback`` (a :class:`Progress` each; None: to
    nobody)."""
    token = _LISTENER.set(callback)
    try:
        yield
    finally:
        _LISTENER.reset(token)


class ProgressBars:
    """A :func:`listen` callback that draws one tqdm bar per (solver, stage) on ``file`` (stderr by default),
    with the report's values as the bar's postfix; a stage that starts again (a second run of the same loop)
    resets its bar. Use as a context manager so the last bar is closed. ``tqdm_options`` go to every bar."""

    def __init__(self, file=None, **tqdm_options) -> None:
        self.file = file
        self.options = {"unit": "it", "leave": False, **tqdm_options}
        self._bar = None
        self._key: tuple[str, str] | None = None

    def __call__(self, p: Progress) -> None:
        from tqdm.auto import tqdm

        if (p.solver, p.stage) != self._key:
            self.close()
            self._key = (p.solver, p.stage)
            self._bar = tqdm(total=p.total, desc=f"{p.solver}: {p.stage}", file=self.file, **self.options)
        elif p.step < self._bar.n:
            self._bar.reset(total=p.total)
        if p.values:
            self._bar.set_postfix({k: f"{v:.4g}" for k, v in p.values.items()}, refresh=False)
        step = min(p.step, p.total) if p.total else p.step
        self._bar.update(step - self._bar.n)  # redraws at most every tqdm mininterval

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._bar, self._key = None, None

    def __enter__(self) -> "ProgressBars":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
