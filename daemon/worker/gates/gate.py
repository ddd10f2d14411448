"""What a gate found: the record every acceptance gate returns, and the advice it may carry.

A :class:`Gate` is what was compared, with what limit, whether it passed and, if not, why in
plain words and what the technician should do (``loopcal calibrate --json`` prints its
fields; the HTML report, the upkeep's proposal and the live guidance read them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Gate:
    """One acceptance check's result: what was compared, and if it failed, why and what to do.

    Every gate function returns one; ``loopcal calibrate --json`` prints them as
    ``{"name", "passed", "value", "limit", "reason", "advice"}`` (:meth:`as_dict`).

    Attributes
    ----------
    name : str
        The gate: the name of its entry in
        :data:`~loopcal.daemon.worker.gates.checks.GATES` (``"poses"``, ``"converged"``,
        ..., ``"precision"``).
    passed : bool
        Whether the check passed.
    value : float, int, str or None
        What was compared, for people and JSON (a count, a ratio, or a text with its unit
        such as ``"12.34 mV"``).
    limit : str
        The limit it was compared with, as text (e.g. ``"<= 1000"``).
    reason : str, default ""
        Why it failed, in plain words; empty when it passed.
    advice : str, default ""
        What the technician should do about it; empty when it passed.
    """

    name: str
    passed: bool
    value: float | int | str | None
    limit: str
    reason: str = ""
    advice: str = ""

    def as_dict(self) -> dict:
        """The gate as JSON-ready fields.

        Returns
        -------
        dict
            ``{"name", "passed", "value", "limit", "reason", "advice"}``.
        """
        return asdict(self)

    def line(self) -> str:
        """The gate for people: ``  [pass] name: value (limit ...)``.

        Returns
        -------
        str
            One line; a failed gate adds a ``why:`` line and a ``do:`` line. A float value
            is shown to 4 significant digits.
        """
        mark = "pass" if self.passed else "FAIL"
        value = f"{self.value:.4g}" if isinstance(self.value, float) else str(self.value)
        text = f"  [{mark}] {self.name}: {value} (limit {self.limit})"
        if not self.passed:
            text += f"\n         why: {self.reason}\n         do:  {self.advice}"
        return text

    @classmethod
    def judged(
        cls, name: str, passed: bool, value: float | int | str | None, limit: str,
        reason: Advice, advice: Advice,
    ) -> Gate:  # fmt: skip
        """A gate that carries its reason and advice only if it failed, made only then.

        Parameters
        ----------
        name, passed, value, limit
            As the attributes of the same names.
        reason, advice : Advice
            Why it failed and what to do, each the text or a function making it (called
            only if it failed: the advice may be costly, and a reason's figures may mean
            nothing for a gate that passed).

        Returns
        -------
        Gate
            With ``reason`` and ``advice`` as text if it failed, both empty if it passed.
        """
        if passed:
            return cls(name, passed, value, limit)
        return cls(name, passed, value, limit, advice_text(reason), advice_text(advice))


#: a failing gate's reason or advice, the text or a function that makes it (called only on
#: failure: :class:`loopcal.daemon.worker.coverage.LazyAdvice`)
Advice = str | Callable[[], str]


def advice_text(advice: Advice) -> str:
    """The text of an advice (or of a reason).

    Parameters
    ----------
    advice : Advice
        The text, or a function making it.

    Returns
    -------
    str
        ``advice`` itself, or what calling it returns (only now: it may be costly).
    """
    return advice if isinstance(advice, str) else advice()
