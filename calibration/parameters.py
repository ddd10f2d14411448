"""The 20 kinematic and sensor parameters, the reference geometry, and free/tied/fixed splits.

A full parameter vector ``p`` is a float array of shape ``(20,)`` in the order of :data:`NAMES`.
Lengths are in mm, gains in mm/V. Frame (docs/model.md section 1): origin at the plate's centre of
rotation O, x along O->A1, A2 in the xy-plane, z out of the base towards the plate; hence
``A1 = (A1x, 0, 0)`` and ``A2 = (A2x, A2y, 0)``.

A :class:`ParameterModel` says which parameters are identified (free), which follow another
one by construction (tied) and which are held (fixed). Ties act on changes: a follower moves
by ``ratio`` times its leader's change, so ``A4x`` tied to ``A1x`` with ratio -1 keeps
``A4x = -A1x`` whenever the start satisfies it (docs/model.md section 3). ``PRESETS`` holds
the named models (``"paper7"``, ``"offsets"``, ``"all"``, ``"d01"`` .. ``"d04"``);
``PAPER7`` is the paper's: d01..d04, A1x, A2x, A2y free, with A3x = -A2x, A3y = -A2y and
A4x = -A1x tied.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from .defaults import DEFAULT_FREE
from .errors import ParameterError

#: the 20 parameter names, in the order of a full vector
NAMES: tuple[str, ...] = (
    "A1x", "A2x", "A2y",
    "A3x", "A3y", "A3z",
    "A4x", "A4y", "A4z",
    "k1", "k2", "k3",
    "S1", "S2", "S3", "S4",
    "d01", "d02", "d03", "d04",
)  # fmt: skip
N_PARAMS = len(NAMES)
#: name -> position in a full vector
INDEX: dict[str, int] = {name: i for i, name in enumerate(NAMES)}
#: name -> unit: "mm/V" for the gains S1..S4, "mm" for the rest
UNITS: dict[str, str] = {n: ("mm/V" if n.startswith("S") else "mm") for n in NAMES}
GROUPS: dict[str, tuple[str, ...]] = {
    "base": NAMES[0:9],
    "plate": NAMES[9:12],
    "gains": NAMES[12:16],
    "offsets": NAMES[16:20],
}
# Slices into a full vector.
SL_GAIN = slice(12, 16)
SL_OFFSET = slice(16, 20)
I_K1, I_K2, I_K3 = 9, 10, 11

# Base point coordinates as (point, axis) -> parameter index; the rest are structural zeros.
BASE_COORDS: dict[tuple[int, int], int] = {
    (0, 0): 0,
    (1, 0): 1, (1, 1): 2,
    (2, 0): 3, (2, 1): 4, (2, 2): 5,
    (3, 0): 6, (3, 1): 7, (3, 2): 8,
}  # fmt: skip

# Reference design (docs/model.md section 10).
#: mm: each actuator moves +-37.5 mm about its home length
STROKE_MM = 37.5
GAIN_NOMINAL = 3.75  #: mm/V: +-10 V spans the +-37.5 mm stroke
STROKE_VOLTS = STROKE_MM / GAIN_NOMINAL  #: 10 V, the LVDT conditioner's span
OFFSET_NOMINAL = 97.4  #: mm: actuator length at home, where V = 0
PLATE_RADIUS = 100.0
B1_AZIMUTH_DEG, B2_AZIMUTH_DEG, B_ELEVATION_DEG = 57.4, 237.4, 45.0

#: the reference design as a full vector, shape (20,), read-only (a copy: :func:`nominal`)
NOMINAL: np.ndarray = np.array(
    [
        68.7, -28.8, 62.4,
        28.8, -62.4, 0.0,
        -68.7, 0.0, 0.0,
        PLATE_RADIUS, PLATE_RADIUS, PLATE_RADIUS * np.sqrt(2.0),
        *([GAIN_NOMINAL] * 4),
        *([OFFSET_NOMINAL] * 4),
    ]
)  # fmt: skip
NOMINAL.setflags(write=False)


def nominal() -> np.ndarray:
    """A writable copy of the reference parameter vector.

    Returns
    -------
    ndarray, shape (20,)
        :data:`NOMINAL` (the reference design, docs/model.md section 10), in the order of
        :data:`NAMES`: mm, and mm/V for the gains S1..S4.
    """
    return NOMINAL.copy()


def index_of(name: str) -> int:
    """Position of a parameter in the full vector.

    Parameters
    ----------
    name : str
        One of :data:`NAMES`, e.g. ``"d01"``.

    Returns
    -------
    int
        Its index, 0..19.

    Raises
    ------
    ParameterError
        If the name is not a parameter (the message lists the known ones).
    """
    try:
        return INDEX[name]
    except KeyError:
        raise ParameterError(
            f"unknown parameter {name!r}; known parameters are {', '.join(NAMES)}"
        ) from None


def to_dict(p: np.ndarray) -> dict[str, float]:
    """A full vector as ``{name: value}``.

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector (mm, mm/V).

    Returns
    -------
    dict of str to float
        Every parameter by name, in the order of :data:`NAMES`.

    Raises
    ------
    ParameterError
        If ``p`` fails :func:`check_vector`.
    """
    p = check_vector(p)
    return {name: float(v) for name, v in zip(NAMES, p, strict=True)}


def from_dict(values: Mapping[str, float], base: np.ndarray | None = None) -> np.ndarray:
    """A full vector from ``{name: value}``.

    Parameters
    ----------
    values : mapping of str to float
        Values by parameter name, in the parameter's unit (mm, or mm/V for S1..S4).
    base : array_like, shape (20,), optional
        Values of the parameters not named; default :data:`NOMINAL`.

    Returns
    -------
    ndarray, shape (20,)
        A new vector. It is not checked as a whole (:func:`check_vector` does that).

    Raises
    ------
    ParameterError
        If a name is unknown, a value is not finite, or ``base`` fails
        :func:`check_vector`.
    """
    p = nominal() if base is None else check_vector(base).copy()
    for name, value in values.items():
        v = float(value)
        if not np.isfinite(v):
            raise ParameterError(f"parameter {name} is not finite ({value!r})")
        p[index_of(name)] = v
    return p


def check_vector(p: np.ndarray) -> np.ndarray:
    """Validate a full parameter vector.

    Parameters
    ----------
    p : array_like, shape (20,)
        Full parameter vector in the order of :data:`NAMES` (mm, mm/V).

    Returns
    -------
    ndarray, shape (20,)
        ``p`` as a float array (not a copy if it already was one).

    Raises
    ------
    ParameterError
        If the shape is not (20,), a value is not finite, a plate size k1..k3 or a gain
        S1..S4 is not positive, or k1, k2, k3 do not form a triangle.
    """
    p = np.asarray(p, dtype=float)
    if p.shape != (N_PARAMS,):
        raise ParameterError(f"a parameter vector has shape ({N_PARAMS},), got {p.shape}")
    bad = [NAMES[i] for i in np.flatnonzero(~np.isfinite(p))]
    if bad:
        raise ParameterError(f"parameters not finite: {', '.join(bad)}")
    nonpos = [NAMES[i] for i in range(I_K1, SL_GAIN.stop) if p[i] <= 0]
    if nonpos:
        raise ParameterError(f"plate sizes and gains must be positive: {', '.join(nonpos)}")
    k1, k2, k3 = p[I_K1], p[I_K2], p[I_K3]
    with np.errstate(over="ignore"):  # k1 + k2 past the largest float is inf: still right
        triangle = abs(k1 - k2) < k3 < k1 + k2
    if not triangle:
        raise ParameterError(f"k1={k1}, k2={k2}, k3={k3} do not form a triangle")
    return p


@dataclass(frozen=True)
class Tie:
    """``follower`` changes by ``ratio`` times the change of ``leader``.

    Names are checked when a :class:`ParameterModel` is built from the tie.

    Parameters
    ----------
    follower : str
        The tied parameter (not free).
    leader : str
        The free parameter it follows.
    ratio : float, default 1.0
        Change of the follower per unit change of the leader; -1 keeps
        ``follower = -leader`` when the start satisfies it.
    """

    follower: str
    leader: str
    ratio: float = 1.0


@dataclass(frozen=True)
class ParameterModel:
    """A split of the 20 parameters into free, tied and fixed.

    Parameters
    ----------
    free : sequence of str
        Names of the identified parameters, in the order of the free vector ``x``.
    ties : sequence of Tie, optional
        Followers that move with a free leader. Every other parameter is fixed.

    Raises
    ------
    ParameterError
        If no parameter is free, a name is unknown or listed twice as free, a follower is
        also free or tied twice, a leader is not free, or a ratio is not finite.

    See Also
    --------
    PRESETS : named models; PAPER7, the paper's seven free parameters and three ties.

    Notes
    -----
    A step ``dx`` of the free values moves the full vector by ``dp = T @ dx``
    (:attr:`tie_matrix`): column j of ``T`` has a 1 at free parameter j and the ratio of
    each of its followers.
    """

    free: tuple[str, ...]
    ties: tuple[Tie, ...] = ()
    _T: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        free = tuple(self.free)
        object.__setattr__(self, "free", free)
        object.__setattr__(self, "ties", tuple(self.ties))
        if not free:
            raise ParameterError("no free parameters: choose at least one to identify")
        for name in free:
            index_of(name)
        dup = sorted({n for n in free if free.count(n) > 1})
        if dup:
            raise ParameterError(f"parameters listed twice as free: {', '.join(dup)}")
        T = np.zeros((N_PARAMS, len(free)))
        for j, name in enumerate(free):
            T[INDEX[name], j] = 1.0
        followers: set[str] = set()
        for tie in self.ties:
            index_of(tie.follower)
            index_of(tie.leader)
            if tie.follower in free:
                raise ParameterError(f"{tie.follower} is free and cannot also be tied")
            if tie.leader not in free:
                raise ParameterError(
                    f"{tie.follower} is tied to {tie.leader}, which is not free; "
                    f"free it or drop the tie"
                )
            if tie.follower in followers:
                raise ParameterError(f"{tie.follower} is tied twice")
            if not np.isfinite(tie.ratio):
                raise ParameterError(f"tie ratio of {tie.follower} is not finite")
            followers.add(tie.follower)
            T[INDEX[tie.follower], free.index(tie.leader)] = tie.ratio
        T.setflags(write=False)
        object.__setattr__(self, "_T", T)

    @property
    def n_free(self) -> int:
        """Number of free parameters, n."""
        return len(self.free)

    @property
    def tied(self) -> tuple[str, ...]:
        """Names of the followers, in the order of the ties."""
        return tuple(t.follower for t in self.ties)

    @property
    def fixed(self) -> tuple[str, ...]:
        """Names of the parameters neither free nor tied, in the order of :data:`NAMES`."""
        moving = set(self.free) | set(self.tied)
        return tuple(n for n in NAMES if n not in moving)

    @property
    def free_index(self) -> np.ndarray:
        """Positions of the free parameters in the full vector, int array of shape (n,)."""
        return np.array([INDEX[n] for n in self.free], dtype=int)

    @property
    def tie_matrix(self) -> np.ndarray:
        """``T``, shape (20, n_free): ``dp = T @ dx``. Maps a free step to a full step.

        Read-only. Passed as ``directions`` to the Jacobians, it gives derivatives with
        respect to the free values.
        """
        return self._T

    def free_values(self, p: np.ndarray) -> np.ndarray:
        """The free vector ``x`` of a full vector.

        Parameters
        ----------
        p : array_like, shape (20,)
            Full parameter vector.

        Returns
        -------
        ndarray, shape (n_free,)
            Its free parameters, in the order of :attr:`free` (mm, mm/V).
        """
        return np.asarray(p, dtype=float)[self.free_index]

    def expand(self, x: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Full vector for free values ``x``: ``base`` moved by ``T @ (x - x_base)``.

        Parameters
        ----------
        x : array_like, shape (n_free,)
            Free values, in the order of :attr:`free`.
        base : array_like, shape (20,)
            The full vector whose fixed parameters are kept and whose free values
            ``x_base`` the step is measured from.

        Returns
        -------
        ndarray, shape (20,)
            The free parameters set to ``x``, each follower moved by its ratio times its
            leader's change, the fixed parameters as in ``base``. Not validated.
        """
        base = np.asarray(base, dtype=float)
        return base + self._T @ (np.asarray(x, dtype=float) - self.free_values(base))

    def describe(self) -> str:
        """The split in words, e.g. ``"free: d01, A1x; tied: A4x = -A1x"``.

        Returns
        -------
        str
            The free names and, if any, each tie as ``follower = [ratio*]leader``.
        """
        ties = ", ".join(
            f"{t.follower} = {'-' if t.ratio == -1 else '' if t.ratio == 1 else f'{t.ratio:g}*'}"
            f"{t.leader}"
            for t in self.ties
        )
        return f"free: {', '.join(self.free)}" + (f"; tied: {ties}" if ties else "")

    @classmethod
    def parse(cls, free: str | Iterable[str], ties: str | Iterable[str] = ()) -> ParameterModel:
        """Build from text: ``free="d01,d02,A1x"`` (or a preset name), ``ties="A3x=-A2x,A4x=-A1x"``.

        Parameters
        ----------
        free : str or iterable of str
            Comma-separated names, or one string per name. A string that is a key of
            :data:`PRESETS` (with no ``ties``) returns that preset.
        ties : str or iterable of str, optional
            Comma-separated ties, or one string per tie, each ``follower=leader``,
            ``follower=-leader`` or ``follower=0.5*leader``.

        Returns
        -------
        ParameterModel

        Raises
        ------
        ParameterError
            If a tie lacks ``=``, a ratio is not a number, or the model is invalid.
        """
        if isinstance(free, str):
            key = free.strip()
            if key in PRESETS and not ties:
                return PRESETS[key]
            free = [s.strip() for s in key.split(",") if s.strip()]
        if isinstance(ties, str):
            ties = [s.strip() for s in ties.split(",") if s.strip()]
        parsed = []
        for text in ties:
            if "=" not in text:
                raise ParameterError(f"tie {text!r} must read follower=leader")
            follower, rhs = (s.strip() for s in text.split("=", 1))
            ratio = 1.0
            if "*" in rhs:
                r, rhs = rhs.split("*", 1)
                try:
                    ratio = float(r)
                except ValueError:
                    raise ParameterError(f"tie {text!r}: ratio {r!r} is not a number") from None
            elif rhs.startswith("-"):
                ratio, rhs = -1.0, rhs[1:]
            parsed.append(Tie(follower, rhs.strip(), ratio))
        return cls(tuple(free), tuple(parsed))


PAPER_TIES = (Tie("A3x", "A2x", -1.0), Tie("A3y", "A2y", -1.0), Tie("A4x", "A1x", -1.0))
PRESETS: dict[str, ParameterModel] = {
    "paper7": ParameterModel(("d01", "d02", "d03", "d04", "A1x", "A2x", "A2y"), PAPER_TIES),
    "offsets": ParameterModel(("d01", "d02", "d03", "d04")),
    "all": ParameterModel(NAMES),
}
for _i in range(1, 5):
    PRESETS[f"d0{_i}"] = ParameterModel((f"d0{_i}",))
PAPER7 = PRESETS[DEFAULT_FREE]
