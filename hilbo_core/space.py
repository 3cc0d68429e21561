"""Parameter spaces: bounds, units, linear inequality constraints and derived parameters.

A :class:`ParameterSpace` is the feasible set the optimizer searches. Optimisation happens in the
unit cube (``u = (x - lower) / (upper - lower)``); constraints are linear in the raw parameters,
so they stay linear in the unit cube and the acquisition maximiser can honour them exactly.
"""

from __future__ import annotations

import enum
import math
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linprog
from scipy.stats import qmc

from hilbo_core.errors import ConfigError, InfeasibleError

__all__ = [
    "DerivedParameter",
    "DesignKind",
    "LinearConstraint",
    "Parameter",
    "ParameterSpace",
    "parse_linear_expression",
]

# sample_unit: Sobol points drawn per call (memory: 2^20 × d floats), the draws after which a
# space without a feasible point is declared too thin (the old limit's order of magnitude), and
# the most draws for one request (2^27: 1,000,000 points, the largest [protocol] n_candidates,
# at a feasible fraction down to ~1/100).
_SOBOL_CHUNK = 2**20
_THIN_DRAWS = 2**17
_MAX_SOBOL_DRAWS = 2**27

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
_TERM = re.compile(r"\s*([+-]?)\s*(?:(\d+(?:\.\d*)?(?:[eE][+-]?\d+)?)\s*\*?\s*)?([A-Za-z_][A-Za-z0-9_]*)?\s*")
_FEAS_TOL = 1e-9


class DesignKind(enum.Enum):
    """How the exploration bout's settings are chosen (:meth:`ParameterSpace.design`)."""

    # The default: the setting nearest the feasible set's centre (where a lab starts, and where
    # CMA-ES starts too), then the first feasible points of a second scrambled Sobol sequence: Kim et al. 2019
    # §IV.A.3's "evenly distributed pseudo-random set of parameters".
    SOBOL = "sobol"
    # The centre, then greedy maximin from a Sobol pool (the design of earlier versions). With few
    # points in many dimensions maximin pushes the points after the first to the boundary of the
    # feasible set (the points farthest from each other are near its corners: in hip_6d 85 % lie
    # within 0.02 of a bound or constraint, against 36 % of Sobol's; tests/hilbo_core/
    # test_space.py), i.e. at extremes of force and timing, which tell the GP little about the
    # interior.
    MAXIMIN = "maximin"
    # No centre point: the first n feasible points of one scrambled Sobol sequence. The
    # simulation study of Kim et al. 2019 (§III.2, Fig. 2) starts from such a set; the centre of
    # a test function's domain is Ackley's optimum and near Levy's, so a design that starts there
    # begins the study at (nearly) the answer. For the benchmarks; a lab starts at the centre.
    SOBOL_ONLY = "sobol_only"


@dataclass(frozen=True)
class Parameter:
    """One optimised parameter.

    Attributes:
        name: Identifier used in dicts, configs and logs.
        lower: Lower bound, in ``unit``.
        upper: Upper bound, in ``unit``; must exceed ``lower``.
        unit: Unit label, e.g. ``"%GC"``, ``"N"``, ``"ratio of F_p"``.
        description: Human-readable meaning.
    """

    name: str
    lower: float
    upper: float
    unit: str = ""
    description: str = ""

    def __post_init__(self) -> None:
        if not _NAME.match(self.name):
            raise ConfigError(f"parameter name {self.name!r} is not an identifier (letters, digits, _)")
        lo, hi = float(self.lower), float(self.upper)
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ConfigError(f"parameter {self.name!r}: bounds must be finite, got [{lo}, {hi}]")
        if not lo < hi:
            raise ConfigError(f"parameter {self.name!r}: lower bound {lo} must be < upper bound {hi}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)


def parse_linear_expression(text: str) -> tuple[dict[str, float], float]:
    """Parse ``"a*x + y - 15"`` into coefficients and a constant.

    Args:
        text: A linear expression of identifiers and numbers joined by ``+``/``-``; a number may
            multiply a name (``0.3*F_p`` or ``0.3 F_p``).

    Returns:
        ``(coeffs, constant)`` with the expression equal to ``sum(coeffs[n]*n) + constant``.

    Raises:
        ConfigError: The text is not such an expression.
    """
    coeffs: dict[str, float] = {}
    constant = 0.0
    pos = 0
    s = text.strip()
    if not s:
        raise ConfigError("empty linear expression")
    first = True
    while pos < len(s):
        m = _TERM.match(s, pos)
        if m is None or m.end() == pos:
            raise ConfigError(f"cannot parse linear expression {text!r} at {s[pos:]!r}")
        sign_txt, num_txt, name = m.groups()
        if not first and not sign_txt:
            raise ConfigError(f"expected '+' or '-' in {text!r} at {s[pos:]!r}")
        if num_txt is None and name is None:
            raise ConfigError(f"dangling sign in linear expression {text!r}")
        sign = -1.0 if sign_txt == "-" else 1.0
        value = sign * (float(num_txt) if num_txt is not None else 1.0)
        if name is None:
            constant += value
        else:
            coeffs[name] = coeffs.get(name, 0.0) + value
        pos = m.end()
        first = False
    return coeffs, constant


@dataclass(frozen=True)
class LinearConstraint:
    """A linear inequality ``sum(coeffs[name] * x[name]) <= upper`` in raw units.

    Build one from text with :meth:`parse`, e.g. ``LinearConstraint.parse("t_on <= t_p - 15")``.
    """

    coeffs: Mapping[str, float]
    upper: float
    text: str = ""

    @classmethod
    def parse(cls, text: str) -> LinearConstraint:
        """Parse ``"lhs <= rhs"`` or ``"lhs >= rhs"`` (both sides linear expressions)."""
        if text.count("<=") + text.count(">=") != 1:
            raise ConfigError(f"constraint {text!r} must contain exactly one '<=' or '>='")
        op = "<=" if "<=" in text else ">="
        lhs_txt, rhs_txt = text.split(op)
        lc, lk = parse_linear_expression(lhs_txt)
        rc, rk = parse_linear_expression(rhs_txt)
        if op == ">=":
            lc, lk, rc, rk = rc, rk, lc, lk
        coeffs = dict(lc)
        for name, c in rc.items():
            coeffs[name] = coeffs.get(name, 0.0) - c
        coeffs = {n: c for n, c in coeffs.items() if c != 0.0}
        if not coeffs:
            raise ConfigError(f"constraint {text!r} involves no parameter")
        return cls(coeffs=coeffs, upper=rk - lk, text=text.strip())

    def describe(self) -> str:
        """The constraint as text (its source text when parsed)."""
        if self.text:
            return self.text
        terms = " + ".join(f"{c:g}*{n}" for n, c in self.coeffs.items())
        return f"{terms} <= {self.upper:g}"


@dataclass(frozen=True)
class DerivedParameter:
    """A parameter computed from others, ``value = offset + sum(coeffs[name] * x[name])``.

    Build one from text with :meth:`parse`, e.g. ``DerivedParameter.parse("T3 = T2 + 10")``.
    """

    name: str
    coeffs: Mapping[str, float]
    offset: float = 0.0
    unit: str = ""
    text: str = ""

    @classmethod
    def parse(cls, text: str, unit: str = "") -> DerivedParameter:
        """Parse ``"name = linear expression"``."""
        if text.count("=") != 1 or "<" in text or ">" in text:
            raise ConfigError(f"derived parameter {text!r} must look like 'name = expression'")
        name, expr = (p.strip() for p in text.split("="))
        if not _NAME.match(name):
            raise ConfigError(f"derived parameter name {name!r} is not an identifier")
        coeffs, offset = parse_linear_expression(expr)
        return cls(name=name, coeffs=coeffs, offset=offset, unit=unit, text=text.strip())


class ParameterSpace:
    """A box of named parameters cut by linear inequality constraints.

    Args:
        parameters: The optimised parameters, in order.
        constraints: Linear constraints (objects or text such as ``"t_on <= t_p - 15"``).
        derived: Derived parameters (objects or text such as ``"T3 = T2 + 10"``); they are
            reported in :meth:`to_dict` but not optimised.
        name: Preset name (e.g. ``"hip_6d"``), used to pick the force-profile builder.

    Raises:
        ConfigError: Duplicate or unknown names.
        InfeasibleError: The constraints leave no feasible point (contradictory constraints).
    """

    __slots__ = ("_A", "_b", "constraints", "derived", "name", "parameters")

    def __init__(
        self,
        parameters: Sequence[Parameter],
        constraints: Iterable[LinearConstraint | str] = (),
        derived: Iterable[DerivedParameter | str] = (),
        name: str = "",
    ) -> None:
        params = tuple(parameters)
        if not params:
            raise InfeasibleError("a parameter space needs at least one parameter, got none")
        names = [p.name for p in params]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ConfigError(f"duplicate parameter names: {sorted(dup)}")
        cons = tuple(LinearConstraint.parse(c) if isinstance(c, str) else c for c in constraints)
        ders = tuple(DerivedParameter.parse(d) if isinstance(d, str) else d for d in derived)
        for c in cons:
            unknown = set(c.coeffs) - set(names)
            if unknown:
                raise ConfigError(
                    f"constraint {c.describe()!r} names unknown parameter(s) {sorted(unknown)}; "
                    f"known: {names}"
                )
        for d in ders:
            unknown = set(d.coeffs) - set(names)
            if unknown:
                raise ConfigError(
                    f"derived parameter {d.name!r} uses unknown parameter(s) {sorted(unknown)}"
                )
            if d.name in names:
                raise ConfigError(f"derived parameter {d.name!r} clashes with an optimised one")
        self.parameters: tuple[Parameter, ...] = params
        self.constraints: tuple[LinearConstraint, ...] = cons
        self.derived: tuple[DerivedParameter, ...] = ders
        self.name = name
        A = np.array([[c.coeffs.get(n, 0.0) for n in names] for c in cons], dtype=float)
        self._A = A.reshape(len(cons), len(names))
        self._b = np.array([c.upper for c in cons], dtype=float)
        self._check_nonempty()

    def __repr__(self) -> str:
        return (f"ParameterSpace(name={self.name!r}, names={list(self.names)}, "
                f"constraints={len(self.constraints)})")

    def __eq__(self, other: object) -> bool:
        return isinstance(other, ParameterSpace) and self.to_json() == other.to_json()

    __hash__ = None  # type: ignore[assignment]  # mutable-looking numpy state; compare by value

    # ------------------------------------------------------------------ basic properties
    @property
    def names(self) -> tuple[str, ...]:
        """Names of the optimised parameters, in order."""
        return tuple(p.name for p in self.parameters)

    @property
    def dim(self) -> int:
        """Number of optimised parameters d."""
        return len(self.parameters)

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds, shape (d,)."""
        return np.array([p.lower for p in self.parameters])

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds, shape (d,)."""
        return np.array([p.upper for p in self.parameters])

    @property
    def units(self) -> dict[str, str]:
        """Unit of every parameter, derived ones included."""
        out = {p.name: p.unit for p in self.parameters}
        out.update({d.name: d.unit for d in self.derived})
        return out

    def constraint_matrix(self) -> tuple[np.ndarray, np.ndarray]:
        """Raw-unit constraints ``A @ x <= b``: A (m, d), b (m,)."""
        return self._A.copy(), self._b.copy()

    def unit_constraints(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit-cube constraints ``A_u @ u <= b_u``: A_u (m, d), b_u (m,).

        With ``x = lower + u * span`` the raw constraint ``A x <= b`` becomes
        ``(A * span) u <= b - A lower``.
        """
        span = self.upper - self.lower
        return self._A * span, self._b - self._A @ self.lower

    # ------------------------------------------------------------------ conversions
    def to_unit(self, x: np.ndarray) -> np.ndarray:
        """Raw parameters (..., d) to the unit cube (..., d)."""
        x = np.asarray(x, dtype=float)
        return (x - self.lower) / (self.upper - self.lower)

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        """Unit-cube points (..., d) to raw parameters (..., d)."""
        u = np.asarray(u, dtype=float)
        return self.lower + u * (self.upper - self.lower)

    def to_dict(self, x: np.ndarray) -> dict[str, float]:
        """A raw vector (d,) as ``{name: value}``, derived parameters included."""
        x = np.asarray(x, dtype=float).reshape(-1)
        if x.shape != (self.dim,):
            raise ConfigError(f"expected a vector of {self.dim} parameters, got shape {x.shape}")
        out = {n: float(v) for n, v in zip(self.names, x, strict=True)}
        for d in self.derived:
            out[d.name] = d.offset + sum(c * out[n] for n, c in d.coeffs.items())
        return out

    def from_dict(self, params: Mapping[str, float]) -> np.ndarray:
        """``{name: value}`` to a raw vector (d,).

        Derived parameters may be present (they are ignored); anything else unknown is an error,
        so a typo cannot silently fall back to a default.
        """
        known = set(self.names) | {d.name for d in self.derived}
        unknown = sorted(set(params) - known)
        if unknown:
            raise ConfigError(f"unknown parameter(s) {unknown}; expected {list(self.names)}")
        missing = [n for n in self.names if n not in params]
        if missing:
            raise ConfigError(f"missing parameter(s) {missing}; expected {list(self.names)}")
        return np.array([float(params[n]) for n in self.names])

    # ------------------------------------------------------------------ feasibility
    def feasible_mask(self, x: np.ndarray, tol: float = _FEAS_TOL) -> np.ndarray:
        """Which rows of raw points x (n, d) satisfy bounds and constraints: (n,) bool."""
        x = np.atleast_2d(np.asarray(x, dtype=float))
        span = self.upper - self.lower
        ok = np.all(np.isfinite(x), axis=1)
        ok &= np.all(x >= self.lower - tol * span, axis=1)
        ok &= np.all(x <= self.upper + tol * span, axis=1)
        if len(self._b):
            scale = np.abs(self._A) @ span + 1.0
            ok &= np.all(x @ self._A.T <= self._b + tol * scale, axis=1)
        return ok

    def is_feasible(self, x: np.ndarray | Mapping[str, float], tol: float = _FEAS_TOL) -> bool:
        """True when the raw point (vector or dict) is inside bounds and constraints."""
        vec = self.from_dict(x) if isinstance(x, Mapping) else np.asarray(x, dtype=float)
        return bool(self.feasible_mask(vec.reshape(1, -1), tol)[0])

    def check(self, x: np.ndarray | Mapping[str, float], tol: float = _FEAS_TOL) -> np.ndarray:
        """Validate a raw point and return it as a vector (d,).

        Raises:
            InfeasibleError: Naming the first parameter or constraint that is violated.
        """
        vec = self.from_dict(x) if isinstance(x, Mapping) else np.asarray(x, dtype=float)
        if vec.shape != (self.dim,):
            raise InfeasibleError(f"expected {self.dim} parameters, got shape {vec.shape}")
        for p, v in zip(self.parameters, vec, strict=True):
            span = p.upper - p.lower
            if not math.isfinite(v) or v < p.lower - tol * span or v > p.upper + tol * span:
                raise InfeasibleError(
                    f"parameter {p.name}={float(v):g} is outside its bounds "
                    f"[{p.lower:g}, {p.upper:g}] {p.unit}"
                )
        for c, row, ub in zip(self.constraints, self._A, self._b, strict=True):
            lhs = float(row @ vec)
            if lhs > ub + tol * (np.abs(row) @ (self.upper - self.lower) + 1.0):
                values = ", ".join(f"{n}={vec[self.names.index(n)]:g}" for n in c.coeffs)
                raise InfeasibleError(f"constraint {c.describe()!r} is violated at {values}")
        return vec

    def _check_nonempty(self) -> None:
        """Raise InfeasibleError when bounds and constraints leave no interior point."""
        if not len(self._b):
            return
        # Chebyshev-centre LP in the unit cube: maximise r with A_u u + r*||A_u_i|| <= b_u.
        A_u, b_u = self.unit_constraints()
        norms = np.linalg.norm(A_u, axis=1)
        d = self.dim
        c = np.zeros(d + 1)
        c[-1] = -1.0
        A_ub = np.hstack([A_u, norms[:, None]])
        res = linprog(c, A_ub=A_ub, b_ub=b_u, bounds=[(0.0, 1.0)] * d + [(0.0, None)])
        if res.status != 0 or -res.fun <= 1e-9:
            cons = "; ".join(c.describe() for c in self.constraints)
            raise InfeasibleError(
                f"the constraints leave no feasible point inside the bounds ({cons})"
            )

    # ------------------------------------------------------------------ designs
    def sample_unit(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``n`` feasible unit-cube points by scrambled Sobol with rejection: (n, d).

        Rounds of Sobol points (each at least twice the points still missing, a power of two)
        are drawn until ``n`` are feasible, in chunks of at most ``_SOBOL_CHUNK`` points so that
        a large ``n`` on a space whose feasible fraction is small (hip_6d: about 1/6) does not
        hold millions of infeasible points at once. Any ``n`` works whose points fit in
        ``_MAX_SOBOL_DRAWS`` draws.

        Args:
            n: Number of points wanted (>= 1).
            rng: Seeds the scrambling, so the set is reproducible.

        Raises:
            ConfigError: n < 1.
            InfeasibleError: No feasible point among the first ``_THIN_DRAWS`` draws, or the
                feasible fraction is too small for n points within ``_MAX_SOBOL_DRAWS`` draws.
        """
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ConfigError(f"number of points must be an integer >= 1, got {n!r}")
        # An integer drawn from rng, not rng itself: scipy spawns from a Generator's SeedSequence,
        # which its saved ``bit_generator.state`` does not capture, so a resumed optimizer
        # would draw different candidates.
        sobol = qmc.Sobol(self.dim, scramble=True, seed=int(rng.integers(2**63)))
        A_u, b_u = self.unit_constraints()
        out: list[np.ndarray] = []
        have = drawn = 0
        while have < n:
            m = 2 ** max(6, math.ceil(math.log2(max(2 * (n - have), 2))))
            if have == 0 and drawn >= _THIN_DRAWS:
                raise InfeasibleError(
                    f"no feasible point among {drawn} Sobol points; the feasible region is too thin")
            if drawn + m > _MAX_SOBOL_DRAWS:
                raise InfeasibleError(
                    f"could only find {have} of {n} feasible points in {drawn} Sobol points "
                    f"(feasible fraction {have / max(drawn, 1):.3g}); ask for fewer points")
            while m > 0:  # one round, in chunks: the Sobol sequence continues across calls
                k = min(m, _SOBOL_CHUNK)
                u = sobol.random(k)
                if len(b_u):
                    u = u[np.all(u @ A_u.T <= b_u + 1e-12, axis=1)]
                out.append(u)
                have += len(u)
                drawn += k
                m -= k
        return np.vstack(out)[:n]

    def design(self, n: int, rng: np.random.Generator, pool: int = 512,
               kind: DesignKind | str = DesignKind.SOBOL) -> np.ndarray:
        """A feasible design of n raw points (n, d) for the exploration phase.

        The first point is the feasible pool's point nearest the centre of the feasible set;
        the others follow ``kind`` (:class:`DesignKind`): ``sobol``, the first n − 1 feasible
        points of a second, independently scrambled Sobol sequence (Kim et al. 2019 §IV.A.3: "an evenly
        distributed pseudo-random set of parameters"), or ``maximin``, greedy maximin selection
        from the pool. ``sobol_only`` has no centre point: the first n feasible Sobol points.

        Args:
            n: Number of points (>= 1).
            rng: Seeds the scrambling (and so the whole design).
            pool: Feasible Sobol points the centre (and maximin's points) are chosen from.
            kind: The design (a :class:`DesignKind` or its value).

        Raises:
            ConfigError: n < 1 or an unknown kind.
        """
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
            raise ConfigError(f"number of design points n={n!r}; expected an integer >= 1")
        try:
            kind = DesignKind(kind)
        except ValueError as err:
            raise ConfigError(
                f"design={kind!r}; expected one of {[k.value for k in DesignKind]}") from err
        if kind is DesignKind.SOBOL_ONLY:
            return self.from_unit(self.sample_unit(n, rng))
        cand = self.sample_unit(max(pool, n), rng)
        centre = cand.mean(axis=0)
        first = int(np.argmin(np.linalg.norm(cand - centre, axis=1)))
        if kind is DesignKind.SOBOL:
            rest = self.sample_unit(n - 1, rng) if n > 1 else np.empty((0, self.dim))
            return self.from_unit(np.vstack([cand[first:first + 1], rest]))
        chosen = [first]
        dmin = np.linalg.norm(cand - cand[chosen[0]], axis=1)
        while len(chosen) < n:
            i = int(np.argmax(dmin))
            chosen.append(i)
            dmin = np.minimum(dmin, np.linalg.norm(cand - cand[i], axis=1))
        return self.from_unit(cand[chosen])

    # ------------------------------------------------------------------ serialisation
    def to_json(self) -> dict:
        """JSON-able definition (round-trips through :meth:`from_json`)."""
        return {
            "name": self.name,
            "parameters": [
                {"name": p.name, "lower": p.lower, "upper": p.upper, "unit": p.unit,
                 "description": p.description}
                for p in self.parameters
            ],
            "constraints": [
                {"coeffs": dict(c.coeffs), "upper": c.upper, "text": c.text} for c in self.constraints
            ],
            "derived": [
                {"name": d.name, "coeffs": dict(d.coeffs), "offset": d.offset, "unit": d.unit,
                 "text": d.text}
                for d in self.derived
            ],
        }

    @classmethod
    def from_json(cls, data: Mapping) -> ParameterSpace:
        """Rebuild a space from :meth:`to_json` output."""
        try:
            return cls(
                parameters=[Parameter(**p) for p in data["parameters"]],
                constraints=[LinearConstraint(**c) for c in data.get("constraints", [])],
                derived=[DerivedParameter(**d) for d in data.get("derived", [])],
                name=data.get("name", ""),
            )
        except (KeyError, TypeError) as err:
            raise ConfigError(f"invalid parameter-space definition: {err}") from err
