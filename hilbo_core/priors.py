"""Fast priors (Antonova 2016 §3.3): cheap observations that enter the GP with inflated noise.

Antonova 2016 initialised BO with 100 policies evaluated in short, simplified simulations and "set
higher noise variance level for points collected for the prior, indicating that while the values
obtained during short simulations have some useful indication of the cost, the actual costs …
are expected to differ". In a lab the cheap sources are:

* **short bouts** — settings measured for a few breaths only: the estimator's own σ² already
  grows as the bout shortens, but a short bout is also biased by the unfinished transient, which
  σ² does not capture;
* **a previous session of the same wearer** — full estimates, but from another day: the wearer
  adapts, the suit is donned differently, the baseline drifts;
* **a population table** — other wearers' costs at the same settings: informative about the
  shape of the landscape, not about this wearer's level.

:class:`PriorNoise` turns a source's variance into the variance the GP is told:

    var_prior = factor · var_source + extra_var_w2

(the multiplicative factor says "this estimate is less trustworthy than it claims"; the additive
term is the variance between the source's conditions and today's, which remains even for a
perfectly measured source). :data:`DEFAULT_PRIOR_NOISE` gives one choice per source; Antonova 2016
prints no numbers, so these are ours, stated with their reasons, and a config can override
them (``[priors]`` table of ``hilbo run``).

No I/O here: the bridge reads a CSV or an MCAP log and passes plain rows or evaluation dicts.
Every function validates its input against the space and raises :class:`ConfigError` naming the
offending row index.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from hilbo_core.errors import ConfigError
from hilbo_core.optimizer import PriorObservation
from hilbo_core.space import ParameterSpace

__all__ = [
    "DEFAULT_PRIOR_NOISE",
    "PriorNoise",
    "PriorSource",
    "inflate_variance",
    "priors_from_evaluations",
    "priors_from_rows",
]


class PriorSource(enum.Enum):
    """Kinds of cheap observations (Antonova 2016 §3.3 adapted to HIL sessions)."""

    SHORT_BOUT = "short_bout"
    PREVIOUS_SESSION = "previous_session"
    POPULATION = "population"


@dataclass(frozen=True)
class PriorNoise:
    """How much less a cheap observation is trusted: var = factor · var_source + extra_var_w2.

    Attributes:
        factor: Multiplies the source's own variance (>= 1: a prior is never *more* certain
            than its source says).
        extra_var_w2: Variance in W² added for the difference between the source's conditions
            and today's (>= 0).
    """

    factor: float = 4.0
    extra_var_w2: float = 0.0

    def __post_init__(self) -> None:
        if isinstance(self.factor, bool) or not isinstance(self.factor, int | float) or not (
            math.isfinite(self.factor) and self.factor >= 1.0
        ):
            raise ConfigError(f"PriorNoise.factor={self.factor!r}; expected a number >= 1")
        if isinstance(self.extra_var_w2, bool) or not isinstance(self.extra_var_w2, int | float) or not (
            math.isfinite(self.extra_var_w2) and self.extra_var_w2 >= 0.0
        ):
            raise ConfigError(f"PriorNoise.extra_var_w2={self.extra_var_w2!r}; expected a variance >= 0 W²")
        object.__setattr__(self, "factor", float(self.factor))
        object.__setattr__(self, "extra_var_w2", float(self.extra_var_w2))


DEFAULT_PRIOR_NOISE: Mapping[PriorSource, PriorNoise] = MappingProxyType({
    # Short bouts: the UKF's σ² of an unfinished transient is optimistic about its bias; doubling
    # the standard deviation (factor 4) is the same margin Algorithm 2 effectively gives early
    # stops. No between-condition term: same day, same donning.
    PriorSource.SHORT_BOUT: PriorNoise(factor=4.0, extra_var_w2=0.0),
    # Previous session of the same wearer: its estimates are full-length, but day-to-day
    # variation of walking cost at a fixed setting is a few per cent (≈ 10 W at ≈ 400 W).
    PriorSource.PREVIOUS_SESSION: PriorNoise(factor=2.0, extra_var_w2=10.0**2),
    # Population table: between-subject spread of the cost *at a setting* is large (tens of W);
    # such rows mostly tell the GP where the landscape is low, not how low.
    PriorSource.POPULATION: PriorNoise(factor=1.0, extra_var_w2=30.0**2),
})
"""Default inflation per source (our choices; Antonova 2016 gives none)."""


def inflate_variance(var_w2: float, noise: PriorNoise) -> float:
    """The variance a prior observation enters the GP with: ``factor · var_w2 + extra_var_w2``.

    Args:
        var_w2: The source's own variance in W² (> 0, finite).
        noise: The source's :class:`PriorNoise`.

    Raises:
        ConfigError: ``var_w2`` is not a finite positive number.
    """
    v = _positive_var(var_w2, "var_w2")
    return noise.factor * v + noise.extra_var_w2


def _positive_var(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{what}={value!r} is not a number") from err
    if not (math.isfinite(v) and v > 0.0):
        raise ConfigError(f"{what}={value!r}; expected a finite variance > 0")
    return v


def _number(value: Any, what: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{what}={value!r} is not a number") from err
    if not math.isfinite(v):
        raise ConfigError(f"{what}={value!r}; expected a finite number")
    return v


def _resolve_noise(source: PriorSource | str, noise: PriorNoise | None) -> tuple[PriorSource, PriorNoise]:
    try:
        src = PriorSource(source)
    except ValueError as err:
        raise ConfigError(
            f"prior source {source!r}; expected one of {[s.value for s in PriorSource]}"
        ) from err
    return src, DEFAULT_PRIOR_NOISE[src] if noise is None else noise


def _point(space: ParameterSpace, params: Mapping[str, Any], where: str) -> dict[str, float]:
    try:
        raw = {k: _number(v, f"{where} parameter {k}") for k, v in params.items()}
        x = space.check(raw)
    except ValueError as err:  # ConfigError (unknown/missing) or InfeasibleError (outside)
        raise ConfigError(f"{where}: {err}") from err
    return space.to_dict(x)


def priors_from_rows(
    space: ParameterSpace,
    rows: Sequence[Mapping[str, Any]],
    *,
    source: PriorSource | str = PriorSource.POPULATION,
    noise: PriorNoise | None = None,
    mean_column: str = "mean",
    var_column: str = "var",
    sd_column: str = "sd",
    default_var_w2: float | None = None,
    baseline_w: float | None = None,
    ignore_columns: Collection[str] = ("subject", "source", "note"),
) -> list[PriorObservation]:
    """Prior observations from a table (e.g. the rows of ``csv.DictReader``).

    Each row holds every parameter of the space by name (derived parameters may be present and
    are recomputed), the cost in ``mean_column`` and its uncertainty in ``var_column`` (W²) or
    ``sd_column`` (W); rows without either use ``default_var_w2``. Values may be strings.

    With ``baseline_w`` the table is *relative*: means are fractions of the unassisted cost
    (a population table is more transferable that way) and are multiplied by ``baseline_w``,
    variances by ``baseline_w²``.

    Args:
        space: The space the priors must lie in.
        rows: The table.
        source: Which :class:`PriorSource` (picks the default inflation).
        noise: Inflation; default :data:`DEFAULT_PRIOR_NOISE` [source].
        mean_column, var_column, sd_column: Column names.
        default_var_w2: Variance for rows with neither var nor sd (W², or fraction² if relative).
        baseline_w: This wearer's unassisted cost in W for a relative table, else None.
        ignore_columns: Extra columns that are allowed and ignored.

    Returns:
        One :class:`PriorObservation` per row, ``source`` ``"<source>:row <i>"``.

    Raises:
        ConfigError: Naming the row index (0-based) and the problem: unknown or missing column,
            non-numeric or NaN value, a point outside the space, a non-positive variance.
    """
    src, inflation = _resolve_noise(source, noise)
    if baseline_w is not None:
        baseline_w = _number(baseline_w, "baseline_w")
        if baseline_w <= 0.0:
            raise ConfigError(f"baseline_w={baseline_w!r}; expected the unassisted cost in W (> 0)")
    if default_var_w2 is not None:
        default_var_w2 = _positive_var(default_var_w2, "default_var_w2")
    known_params = set(space.names) | {d.name for d in space.derived}
    meta = {mean_column, var_column, sd_column, *ignore_columns}
    out: list[PriorObservation] = []
    for i, row in enumerate(rows):
        where = f"prior row {i}"
        if not isinstance(row, Mapping):
            raise ConfigError(f"{where}: expected a mapping of column → value, got {type(row).__name__}")
        unknown = sorted(set(row) - known_params - meta)
        if unknown:
            raise ConfigError(
                f"{where}: unknown column(s) {unknown}; expected parameters {list(space.names)}, "
                f"{mean_column!r} and {var_column!r} or {sd_column!r}"
            )
        if mean_column not in row:
            raise ConfigError(f"{where}: missing the cost column {mean_column!r}")
        mean = _number(row[mean_column], f"{where} {mean_column}")
        if row.get(var_column) not in (None, ""):
            var = _positive_var(row[var_column], f"{where} {var_column}")
        elif row.get(sd_column) not in (None, ""):
            sd = _number(row[sd_column], f"{where} {sd_column}")
            var = _positive_var(sd * sd, f"{where} {sd_column}²")
        elif default_var_w2 is not None:
            var = default_var_w2
        else:
            raise ConfigError(
                f"{where}: neither {var_column!r} nor {sd_column!r} is given and no default_var_w2"
            )
        params = _point(space, {k: v for k, v in row.items() if k in known_params}, where)
        if baseline_w is not None:
            mean, var = mean * baseline_w, var * baseline_w**2
        out.append(PriorObservation(params, mean, inflate_variance(var, inflation),
                                    f"{src.value}:row {i}"))
    return out


def priors_from_evaluations(
    space: ParameterSpace,
    evaluations: Sequence[Mapping[str, Any]],
    *,
    source: PriorSource | str = PriorSource.PREVIOUS_SESSION,
    noise: PriorNoise | None = None,
    skip_early_stopped: bool = False,
    label: str = "",
) -> list[PriorObservation]:
    """Prior observations from completed evaluations of an earlier session or short bouts.

    Each evaluation is a plain dict ``{"params": {...}, "mean": W, "var": W², ...}`` — the
    ``evaluations`` of a ``summary.json``, or what the bridge read from an MCAP log's observation
    channel; other keys are ignored except ``stopped_early``.

    Args:
        space: The space the priors must lie in.
        evaluations: The evaluations.
        source: :class:`PriorSource` (default previous session).
        noise: Inflation; default :data:`DEFAULT_PRIOR_NOISE` [source].
        skip_early_stopped: Drop evaluations with ``stopped_early`` true (their estimate ended
            during the transient; they are kept by default because their σ² says so).
        label: Prefix of each observation's ``source`` tag (e.g. the log's file name).

    Returns:
        One :class:`PriorObservation` per kept evaluation.

    Raises:
        ConfigError: Naming the evaluation index: missing keys, NaN mean, non-positive variance,
            a setting outside the space.
    """
    src, inflation = _resolve_noise(source, noise)
    tag = f"{label}:" if label else ""
    out: list[PriorObservation] = []
    for i, ev in enumerate(evaluations):
        where = f"prior evaluation {i}"
        if not isinstance(ev, Mapping):
            raise ConfigError(f"{where}: expected a dict with params, mean, var; got {type(ev).__name__}")
        missing = [k for k in ("params", "mean", "var") if k not in ev]
        if missing:
            raise ConfigError(f"{where}: missing key(s) {missing}; expected params, mean and var")
        if skip_early_stopped and bool(ev.get("stopped_early", False)):
            continue
        if not isinstance(ev["params"], Mapping):
            raise ConfigError(f"{where}: params must be a dict of name → value, got {ev['params']!r}")
        params = _point(space, ev["params"], where)
        mean = _number(ev["mean"], f"{where} mean")
        var = _positive_var(ev["var"], f"{where} var")
        out.append(PriorObservation(params, mean, inflate_variance(var, inflation),
                                    f"{tag}{src.value}:evaluation {i}"))
    return out
