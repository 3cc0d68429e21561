"""The session config: one TOML file, validated on load.

``hilbo config example`` prints a complete commented config (``bridge/config_example.toml``);
``hilbo config check CONFIG.toml`` validates one and prints a summary. In code::

    cfg = load_config("s07.toml")          # or parse_config(text, source="...")
    cfg.protocol.optimizer_config()        # -> hilbo_core OptimizerConfig
    cfg.make_gate()                        # -> bridge.safety.SafeProfileGate (the limits layer)
    cfg.to_json()                          # -> for the log's config channel (raw TOML included)

Tables: ``[session]``, ``[space]``, ``[protocol]``, ``[cart]`` (validated by
:meth:`drivers.cart.CartConfig.from_dict`, see drivers/cart/FORMAT.md), ``[can]``, ``[limits]``
(:class:`bridge.safety.ProfileLimits`), ``[watchdog]``, ``[prior]``, ``[live]`` and
``[validation]``. Every table is declared as a frozen :class:`msgspec.Struct` (ranges as
``Annotated[float, Meta(ge=..., le=...)]``, choices as enums) and decoded by
:func:`drivers.config_model.decode` (:func:`msgspec.convert`, strict); a table whose validated
form is another type (``[space]`` -> :class:`~hilbo_core.space.ParameterSpace`, ``[limits]``,
``[prior]``, ``[can]``'s bus) is decoded into a private Struct of its TOML keys first. The
loader refuses unknown tables and keys (a typo must never fall back silently to a default; the
error names ``table.key``, suggests the closest allowed key and lists them all), checks every
type and range (NaN, ``inf`` and ``true`` are not numbers), and names the key, the value and
what is allowed in every error (:class:`~bridge.errors.BridgeConfigError`). A TOML syntax
error is reported with its line and column. Paths (``session.out_dir``, ``cart.options.path``,
``prior.logs``, ``prior.table``) are relative to the working directory. ``[prior]``
(:class:`PriorConfig`) reads its logs and table on load, so a bad prior is refused before the
session starts. ``[live]`` (:class:`LiveConfig`) turns the Foxglove live view on (bridge/live.py).

Cross-checks after the tables: the space's force-profile builder must build the centre of the
space, per-actuator limits must name actuators the builder produces, and the limits must admit
that centre (a config whose limits refuse the middle of its own space would stall the session);
``hilbo config check`` also samples the space and reports how much of it the limits refuse.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import difflib
import enum
import io
import ipaddress
import math
import os
import re
import sys
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, Literal, TextIO

import can
import msgspec
import numpy as np
from msgspec import Meta

from bridge.argtypes import nonnegative_int
from bridge.collector import GcMode
from bridge.errors import BridgeConfigError
from bridge.outcome import format_params
from bridge.proposals import WorkerKind
from bridge.safety import (
    ACTUATOR_LIMIT_RANGES,
    ProfileLimits,
    SafeProfileGate,
    make_actuator_limits,
    preflight,
)
from drivers.cart import CartConfig
from drivers.cart.pipeline import describe_record
from drivers.config_model import FINITE, decode, range_text, unknown_key_message
from drivers.errors import DriverConfigError
from drivers.exosuit.endpoint import INTERFACE_OPTIONS, CanBusConfig
from drivers.exosuit.rating import RATED_FORCE_N
from drivers.files import read_regular_file
from hilbo_core.errors import ConfigError, InfeasibleError
from hilbo_core.gp import KernelKind
from hilbo_core.optimizer import (
    DEFAULT_ACCEPT_Z,
    FLOOR_ACCEPT_Z,
    OptimizerConfig,
    PriorObservation,
    StoppingKind,
)
from hilbo_core.presets import PRESETS
from hilbo_core.priors import (
    DEFAULT_PRIOR_NOISE,
    PriorNoise,
    PriorSource,
    inflate_variance,
    priors_from_evaluations,
    priors_from_rows,
)
from hilbo_core.profiles import PROFILE_BUILDERS, PROFILE_DOMAINS, build_profile
from hilbo_core.protocol import (
    DEFAULT_BREATH_INTERVAL_S,
    ProtocolKind,
    SessionProtocolConfig,
    expected_end_s,
    protocol_preset,
)
from hilbo_core.space import DerivedParameter, DesignKind, LinearConstraint, Parameter, ParameterSpace

__all__ = [
    "ALLOWED_KEYS",
    "TABLES",
    "BusErrorPolicy",
    "CanConfig",
    "HilboConfig",
    "LiveConfig",
    "PriorConfig",
    "ProtocolConfig",
    "RefitMode",
    "SessionConfig",
    "SpaceConfig",
    "WatchdogConfig",
    "add_config_parser",
    "check_cart_file",
    "check_out_dir",
    "config_warnings",
    "example_config_text",
    "load_config",
    "parse_config",
    "summarize",
]

#: The tables a config may have, in the order the example shows them.
TABLES = ("session", "space", "protocol", "cart", "can", "limits", "watchdog", "prior", "live", "validation")
_REQUIRED_TABLES = ("session", "space", "cart", "can")



# Every table is a msgspec Struct decoded by drivers.config_model.decode: unknown keys refused
# with a suggestion, types and ranges checked, errors naming table.key, the value and the range.
_STRUCT: dict[str, Any] = {"frozen": True, "forbid_unknown_fields": True, "kw_only": True}


# --------------------------------------------------------------------------------------------
# [session]
# --------------------------------------------------------------------------------------------


class SessionConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``[session]``: who walks, and where the session's files go.

    Attributes:
        subject: Subject id, used in file names: letters, digits, ``_ . -``, at most 64.
        body_mass_kg: The wearer's mass in kg, 20–250 (``hip_ankle_4d`` scales its forces by it).
        out_dir: Directory for the session's MCAP log and summary; a leading ``~`` is the home
            folder (``~/hilbo-sessions``), as in a shell.
        notes: Free text copied into the log.
        file_mode: Permission bits of the log and summary as octal text (default ``"0600"``:
            owner only, they hold health data: VO2, heart rate, body mass).
    """

    subject: Annotated[str, Meta(min_length=1, pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$", description=(
        "1-64 letters, digits, '_', '.', '-' (it is used in file names), starting with a letter or digit"))]
    body_mass_kg: Annotated[float, Meta(ge=20.0, le=250.0)]
    out_dir: Path = Path("sessions")
    notes: str = ""
    file_mode: Annotated[str, Meta(min_length=1, pattern=r"^0?[0-7]{3}$", description=(
        'octal permission bits such as "0600" (owner read/write: session files hold health data) '
        'or "0640"'))] = "0600"

    @property
    def file_mode_bits(self) -> int:
        """:attr:`file_mode` as an integer (``0o600``)."""
        return int(self.file_mode, 8)


# --------------------------------------------------------------------------------------------
# [space]
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SpaceConfig:
    """``[space]``: the parameter space, a preset (optionally re-bounded) or defined inline.

    Attributes:
        space: The space; ``space.name`` is the force-profile builder (``hip_6d``, ``hip_ankle_4d``).
        preset: The preset it came from, or None for an inline definition.
    """

    space: ParameterSpace
    preset: str | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"preset": self.preset, "definition": self.space.to_json()}


class _ParameterTable(msgspec.Struct, **_STRUCT):
    name: Annotated[str, Meta(min_length=1)]
    lower: Annotated[float, Meta(ge=-FINITE, le=FINITE)]
    upper: Annotated[float, Meta(ge=-FINITE, le=FINITE)]
    unit: str = ""
    description: str = ""


class _SpaceTable(msgspec.Struct, **_STRUCT):
    preset: Literal[tuple(PRESETS)] | None = None  # type: ignore[valid-type]
    bounds: dict[str, Any] | None = None
    constraints: list[str] = []
    profile: Literal[tuple(PROFILE_BUILDERS)] | None = None  # type: ignore[valid-type]
    parameters: Annotated[list[_ParameterTable], Meta(
        min_length=1, description="one or more [[space.parameters]] tables")] | None = None
    derived: list[str] | None = None


def _parse_texts(texts: Iterable[str], where: str, parse: Any) -> list[Any]:
    out = []
    for i, text in enumerate(texts):
        try:
            out.append(parse(text))
        except ConfigError as err:
            raise BridgeConfigError(f"{where}[{i}] = {text!r}: {err}") from err
    return out


def _parse_space(data: object) -> SpaceConfig:
    t = decode(_SpaceTable, data, "space", BridgeConfigError)
    if (t.preset is None) == (t.parameters is None):
        raise BridgeConfigError(
            "space: give either preset = \"hip_6d\" (or \"hip_ankle_4d\") or an inline definition "
            "([[space.parameters]] tables with profile = ...), "
            + ("not both" if t.preset is not None else "found neither")
        )
    constraints = _parse_texts(t.constraints, "space.constraints", LinearConstraint.parse)
    if t.preset is not None:
        for key in ("profile", "derived"):
            if getattr(t, key) is not None:
                raise BridgeConfigError(
                    f"space.{key} = {data[key]!r:.60}: only for an inline definition; preset "  # type: ignore[index]
                    f"{t.preset!r} fixes it (use space.bounds and space.constraints to narrow a preset)"
                )
        base = PRESETS[t.preset]()
        pairs = [(p.name, Annotated[tuple[float, float], Meta(description=(
            f"[lower, upper] in {p.unit or 'its unit'}"))] | None, None) for p in base.parameters]
        bounds: Any = decode(msgspec.defstruct("bounds", pairs, **_STRUCT), t.bounds or {}, "space.bounds",
                             BridgeConfigError)
        params = list(base.parameters)
        for i, par in enumerate(params):
            if getattr(bounds, par.name) is None:
                continue
            value = t.bounds[par.name]  # type: ignore[index]  # as given (200, not 200.0)
            try:
                params[i] = Parameter(par.name, value[0], value[1], par.unit, par.description)
            except ConfigError as err:
                raise BridgeConfigError(f"space.bounds.{par.name} = {value!r}: {err}") from err
        constraints = [*base.constraints, *constraints]
        derived = list(base.derived)
        name: str = t.preset
    else:
        if t.bounds is not None:
            raise BridgeConfigError(
                "space.bounds re-bounds a preset's parameters; in an inline definition give lower "
                "and upper in each [[space.parameters]] table"
            )
        if t.profile is None:
            raise BridgeConfigError("space.profile is missing: expected one of "
                                    + ", ".join(repr(p) for p in sorted(PROFILE_BUILDERS)))
        name = t.profile
        params = []
        for i, p in enumerate(t.parameters):  # type: ignore[arg-type]
            try:
                params.append(Parameter(p.name, p.lower, p.upper, p.unit, p.description))
            except ConfigError as err:
                raise BridgeConfigError(f"space.parameters[{i}]: {err}") from err
        derived = _parse_texts(t.derived or (), "space.derived", DerivedParameter.parse)
    domains = PROFILE_DOMAINS.get(name, {})
    for i, par in enumerate(params):
        dom = domains.get(par.name)
        if dom is not None and not dom.contains(par.lower, par.upper):
            key = f"space.bounds.{par.name}" if t.preset is not None else f"space.parameters[{i}]"
            raise BridgeConfigError(
                f"{key} = [{par.lower:g}, {par.upper:g}]: expected {dom.text(par.name)} (what the "
                f"{name!r} force-profile builder can build; a setting outside is never sent)")
    try:
        space = ParameterSpace(params, constraints, derived, name=name)
    except (ConfigError, InfeasibleError) as err:
        raise BridgeConfigError(f"space: {err}") from err
    return SpaceConfig(space=space, preset=t.preset)


# --------------------------------------------------------------------------------------------
# [protocol]
# --------------------------------------------------------------------------------------------


class RefitMode(enum.Enum):
    """``[protocol] refit``: when the GP hyperparameters are refitted (see ProtocolConfig)."""

    AHEAD = "ahead"
    AT_PROPOSAL = "at_proposal"


# Kim et al. 2019 §IV.A.3: a 40-minute optimisation bout (SessionProtocolConfig.budget_s)
_DEFAULT_BUDGET_S = SessionProtocolConfig.budget_s
_DEFAULT_BUDGET_MIN = None if _DEFAULT_BUDGET_S is None else _DEFAULT_BUDGET_S / 60.0


class ProtocolConfig(msgspec.Struct, **_STRUCT):
    """``[protocol]``: the walking protocol and the optimizer (Kim et al. 2019 §IV.A.3, Algorithm 1).

    Two bouts: the exploration bout (``n_explore`` settings of ``max_breaths`` breaths each), then
    the optimisation bout until the budget is spent; each starts with ``warmup_s`` of walking
    that is not measured. With ``pause_between_bouts`` the session pauses (assistance off) after
    the exploration bout until the operator resumes.

    Attributes:
        warmup_s: Walking before the first measured breath of each bout (s), 0–1800.
        n_explore: Exploration settings E, 1–200; absent: the protocol's (fast 3, seed 6).
        max_breaths: Breaths per evaluation at most (N), 2–1000.
        window: Algorithm 2's window W in breaths, 0..N−1.
        budget_min: Optimisation-bout budget in minutes of walking from the end of the bout's
            warm-up (setting changes, pauses and the warm-ups after a pause count: walked time), or
            None (:class:`hilbo_core.protocol.SessionProtocolConfig`'s ``budget_s``).
        budget_breaths: Optimisation-bout budget in breaths, or None (at least one budget is set;
            with both, the first spent ends the bout).
        session_min: The whole session's length in minutes of walking from its first breath
            (both bouts, their warm-ups, setting changes and pauses: "a lab has the hour it
            has"), or None (default: the session ends with the optimisation budget).
            With it, the session ends at the first breath past ``session_min`` or when the
            budget is spent, whichever comes first.
        stopping: ``sound`` (default: the σ-scaled rule with a threshold floor, sequential
            reject and accept boundaries that are strict early and relax until ``boundary_s``,
            and the GP-posterior incumbent), ``sound-floor`` (the same on a fixed clock: no
            decision before 60 s, then constant thresholds; the earlier default), ``adaptive``
            (Algorithm 2 + Kim et al. 2019's σ-scaled rule) or ``fixed`` (always N breaths).
        min_decision_s: The sound rule's seconds in a setting before any stop decision, 0–600;
            absent: the rule's (``sound`` 30, ``sound-floor`` 60).
        boundary_s: ``sound``'s seconds in a setting at which its boundaries reach their late
            levels ``a_floor`` and ``accept_z`` (before it they are sqrt(boundary_s / t) times
            higher), 1–600 (default 60).
        a_floor: The sound rule's threshold floor in σ, 0–10.
        accept_stop: The sound rule's accept stop: end a setting already ``accept_z`` σ better
            than the incumbent (default on; off: every candidate that is not rejected walks N
            breaths).
        accept_z: Its margin in σ, 0–10; absent: the rule's (``sound`` 2, reached at
            ``boundary_s``; ``sound-floor`` 3).
        design: The exploration bout's settings: ``sobol`` (the centre, then scrambled Sobol
            points) or ``maximin`` (the centre, then points at the boundary); absent:
            ``sobol`` with the sound rule, ``maximin`` with Kim et al. 2019's rules
            (:class:`hilbo_core.space.DesignKind`).
        seed: The optimizer's random seed (>= 0).
        xi: Expected Improvement's ξ (Kim et al. 2019 §II.B sign convention).
        kernel: ``matern52`` or ``se``.
        prior_mean_sd: The GP's constant prior mean in SDs of the measured costs above their
            average, 0-3; absent: 0.5 with the sound rules (an unmeasured setting is expected to
            be worse than the settings the search chose to measure), 0 with Kim et al. 2019's
            rules (their GP: the average) (:class:`hilbo_core.optimizer.OptimizerConfig`).
        n_candidates: Feasible Sobol candidates per acquisition maximisation.
        n_local: Candidates refined locally per acquisition maximisation.
        pause_between_bouts: Pause for the operator between the bouts; absent: the protocol's
            (fast: no, one continuous walk; seed: yes).
        protocol: The walking protocol by name (:class:`hilbo_core.protocol.ProtocolKind`):
            ``fast`` (default: the first optimisation proposal at about minute 10, one warm-up
            when no pause separates the bouts, the recommendation confirmed in the last
            minutes) or ``seed`` (Kim et
            al. 2019 §IV.A.3: a warm-up before each bout, N breaths per exploration setting);
            absent: ``fast`` with the sound rule, ``seed`` with the seed's rules (like ``design``).
        confirm_min: Minutes at the session's end reserved to measure the recommended setting
            in full ("recommended, confirmed at X ± Y W"), 0-120; 0: none; absent: the
            protocol's (fast: 4, seed: none).
        explore_rel_sd: Exploration settings end once their estimate's SD is at most this
            fraction of it (after ``min_decision_s``), 0-0.5; 0 or absent: N breaths (both
            protocols: ending them early cost regret on the realistic wearer).
        short_pause_s: A pause (a fault, the operator's ``p``) at most this long, in seconds of
            walking (breath time), 0–600, ends without a warm-up: the setting it abandoned is
            measured again at once from the body's current level; a longer pause ends with the
            bout's warm-up (:class:`hilbo_core.protocol.SessionProtocolConfig`, where the 30 s
            default is argued from VO2 kinetics). 0: every pause ends with a warm-up.
        refit: When the GP hyperparameters are refitted: ``ahead`` (default: on the completed
            evaluations while the next setting is measured, so the proposal after a stop
            decision only conditions the GP on every observation and maximises EI; the
            hyperparameters lag the data by one evaluation) or ``at_proposal`` (inside every
            proposal, as Kim et al. 2019 describes it; adds 10–60 ms to each stop -> push).
        proposal_worker: Where proposals and fits run: ``process`` (default: a worker process,
            off the CAN traffic's GIL) or ``thread``.
        gc: When full garbage collections may stop the event loop: ``freeze`` (default: at
            quiet points of the session, bridge/collector.py) or ``automatic`` (CPython's
            schedule: a 40–60 ms pause at a moment nothing chooses, every few minutes).
    """

    # The defaults are declared once: the protocol's in hilbo_core.protocol, the optimizer's in
    # hilbo_core.optimizer (a dataclass field's default is its class attribute). window's upper
    # bound is max_breaths - 1 (__post_init__); the budgets are either-or (_parse_protocol).
    warmup_s: Annotated[float, Meta(ge=0.0, le=1800.0)] = SessionProtocolConfig.warmup_s
    n_explore: Annotated[int, Meta(ge=1, le=200)] | None = None
    max_breaths: Annotated[int, Meta(ge=2, le=1000)] = OptimizerConfig.max_breaths
    window: Any = OptimizerConfig.window  # an int in [0, max_breaths - 1]: __post_init__
    budget_min: Annotated[float, Meta(gt=0.0, le=1440.0)] | None = _DEFAULT_BUDGET_MIN
    budget_breaths: Annotated[int, Meta(ge=1, le=100_000)] | None = SessionProtocolConfig.budget_breaths
    session_min: Annotated[float, Meta(gt=0.0, le=1440.0)] | None = None
    stopping: StoppingKind = OptimizerConfig.stopping
    min_decision_s: Annotated[float, Meta(ge=0.0, le=600.0)] | None = None
    boundary_s: Annotated[float, Meta(ge=1.0, le=600.0)] = OptimizerConfig.boundary_s
    a_floor: Annotated[float, Meta(ge=0.0, le=10.0)] = OptimizerConfig.a_floor
    accept_stop: bool = OptimizerConfig.accept_z is not None
    accept_z: Annotated[float, Meta(ge=0.0, le=10.0)] | None = None
    design: DesignKind | None = OptimizerConfig.design
    seed: Annotated[int, Meta(ge=0, le=2**63 - 1)] = OptimizerConfig.seed
    xi: Annotated[float, Meta(ge=-1e6, le=1e6)] = OptimizerConfig.xi
    kernel: KernelKind = OptimizerConfig.kernel
    prior_mean_sd: Annotated[float, Meta(ge=0.0, le=3.0)] | None = None
    n_candidates: Annotated[int, Meta(ge=16, le=1_000_000)] = OptimizerConfig.n_candidates
    n_local: Annotated[int, Meta(ge=0, le=100)] = OptimizerConfig.n_local
    pause_between_bouts: bool | None = None
    protocol: ProtocolKind | None = None
    confirm_min: Annotated[float, Meta(ge=0.0, le=120.0)] | None = None
    explore_rel_sd: Annotated[float, Meta(ge=0.0, le=0.5)] | None = None
    short_pause_s: Annotated[float, Meta(ge=0.0, le=600.0)] = SessionProtocolConfig.short_pause_s
    refit: RefitMode = RefitMode.AHEAD
    proposal_worker: WorkerKind = WorkerKind.PROCESS
    gc: GcMode = GcMode.FREEZE

    def __post_init__(self) -> None:
        w = self.window
        if isinstance(w, bool) or not isinstance(w, int) or not 0 <= w < self.max_breaths:
            raise ValueError(f"window = {w!r}: expected an integer in "
                             f"{range_text(0, self.max_breaths - 1)}")
        if self.session_min is not None and 60.0 * self.session_min <= self.warmup_s:
            raise ValueError(f"session_min = {self.session_min:g}: expected more minutes than the "
                             f"warm-up (warmup_s = {self.warmup_s:g} s): the session would end "
                             "before its first setting")
        ends = {k: v for k, v in (("budget_min", self.budget_min), ("session_min", self.session_min))
                if v is not None}
        if self.confirm_min and ends and self.confirm_min >= min(ends.values()):
            key = min(ends, key=ends.__getitem__)
            raise ValueError(f"confirm_min = {self.confirm_min:g}: expected fewer minutes than "
                             f"{key} = {ends[key]:g} (the confirmation is the end of the session's "
                             "optimisation time, not all of it)")

    @property
    def protocol_kind(self) -> ProtocolKind:
        """The walking protocol: ``protocol``, else ``fast`` with the sound rule and ``seed``
        with the seed's rules (so ``adaptive`` and ``fixed`` stay the methods they were)."""
        if self.protocol is not None:
            return self.protocol
        return ProtocolKind.FAST if self.stopping.is_sound else ProtocolKind.SEED

    @property
    def explore_points(self) -> int:
        """E: ``n_explore``, else the protocol's."""
        if self.n_explore is not None:
            return self.n_explore
        return int(protocol_preset(self.protocol_kind)[1]["n_explore"])

    @property
    def pauses_between_bouts(self) -> bool:
        """``pause_between_bouts``, else the protocol's."""
        if self.pause_between_bouts is not None:
            return self.pause_between_bouts
        return bool(protocol_preset(self.protocol_kind)[0]["pause_between_bouts"])

    @property
    def accept_margin_z(self) -> float | None:
        """The accept stop's margin in σ: ``accept_z``, else the rule's; None with
        ``accept_stop`` off."""
        if not self.accept_stop:
            return None
        if self.accept_z is not None:
            return self.accept_z
        return FLOOR_ACCEPT_Z if self.stopping is StoppingKind.SOUND_FLOOR else DEFAULT_ACCEPT_Z

    @property
    def budget_s(self) -> float | None:
        """The time budget in seconds, or None."""
        return None if self.budget_min is None else 60.0 * self.budget_min

    def session_protocol_config(self) -> SessionProtocolConfig:
        """The :class:`hilbo_core.protocol.SessionProtocolConfig` of this protocol."""
        named = protocol_preset(self.protocol_kind)[0]
        if self.confirm_min is not None:  # 0: no confirmation
            named["confirm_s"] = 60.0 * self.confirm_min if self.confirm_min > 0 else None
        named.update(
            warmup_s=self.warmup_s, n_explore=self.explore_points, max_breaths=self.max_breaths,
            session_s=None if self.session_min is None else 60.0 * self.session_min, budget_s=self.budget_s,
            budget_breaths=self.budget_breaths, pause_between_bouts=self.pauses_between_bouts,
            short_pause_s=self.short_pause_s,
        )
        return SessionProtocolConfig(**named)

    def optimizer_config(self, *, with_budget: bool = True) -> OptimizerConfig:
        """The :class:`hilbo_core.optimizer.OptimizerConfig` of this protocol.

        Args:
            with_budget: Give the optimizer the budgets (its own counter: breath time inside
                evaluations). False for an optimizer driven by a
                :class:`hilbo_core.protocol.SessionProtocol`, which ends the session on walking
                time (:meth:`session_protocol_config`).
        """
        named = protocol_preset(self.protocol_kind)[1]
        if self.explore_rel_sd is not None:  # 0: every exploration setting measured for N breaths
            named["explore_rel_sd"] = self.explore_rel_sd if self.explore_rel_sd > 0 else None
        named["n_explore"] = self.explore_points
        return OptimizerConfig(
            **named, max_breaths=self.max_breaths, window=self.window,
            budget_s=self.budget_s if with_budget else None,
            budget_breaths=self.budget_breaths if with_budget else None, stopping=self.stopping,
            min_decision_s=self.min_decision_s, boundary_s=self.boundary_s, a_floor=self.a_floor,
            accept_z=self.accept_margin_z, design=self.design,
            seed=self.seed, xi=self.xi, kernel=self.kernel, prior_mean_sd=self.prior_mean_sd,
            n_candidates=self.n_candidates,
            n_local=self.n_local, refit_lag=1 if self.refit is RefitMode.AHEAD else 0,
        )

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return _jsonable(self)


def _parse_protocol(data: object) -> ProtocolConfig:
    if isinstance(data, Mapping) and ("budget_min" in data or "budget_breaths" in data):
        data = {"budget_min": None, "budget_breaths": None, **data}  # either budget, or both
    cfg = decode(ProtocolConfig, data, "protocol", BridgeConfigError)
    try:
        cfg.optimizer_config()  # the optimizer's own validation is the final word
    except ConfigError as err:
        raise BridgeConfigError(f"protocol: {err}") from err
    return cfg


# --------------------------------------------------------------------------------------------
# [cart]
# --------------------------------------------------------------------------------------------

def _parse_cart(data: object) -> CartConfig:
    if not isinstance(data, Mapping):
        raise BridgeConfigError(f"cart = {data!r:.60}: expected a table ([cart])")
    try:
        return CartConfig.from_dict(data, "cart")
    except DriverConfigError as err:  # the same message: drivers.config_model words both
        raise BridgeConfigError(str(err)) from err


# --------------------------------------------------------------------------------------------
# [can]
# --------------------------------------------------------------------------------------------


class _CanTiming(msgspec.Struct, **_STRUCT):
    heartbeat_period_ms: Annotated[float, Meta(ge=5.0, le=50.0)] = 20.0
    push_timeout_ms: Annotated[float, Meta(ge=10.0, le=5000.0)] = 250.0
    push_retries: Annotated[int, Meta(ge=0, le=10)] = 3
    segment_pace_ms: Annotated[float, Meta(ge=0.0, le=50.0)] = 1.0


_Interface = Literal[tuple(sorted(can.VALID_INTERFACES))]  # type: ignore[valid-type]


class _CanTable(_CanTiming, **_STRUCT):
    """``[can]`` as the TOML gives it: the bus's keys and the timing."""

    interface: _Interface
    channel: Annotated[Annotated[str, Meta(min_length=1)] | int, Meta(
        description="a non-empty string or an integer (e.g. 'vcan0', 'PCAN_USBBUS1', 0)")]
    bitrate: Annotated[int, Meta(ge=10_000, le=8_000_000)] = 1_000_000
    options: dict[str, Any] = {}


class CanConfig(_CanTiming, **_STRUCT):
    """``[can]``: the exosuit's CAN bus and the timing of the bridge's side of the protocol.

    Attributes:
        bus: Interface, channel, bitrate and python-can options (drivers/PROTOCOL.md,
            "Transports").
        heartbeat_period_ms: BridgeHeartbeat period, 5–50 ms (the device's watchdog is 100 ms,
            so at least two heartbeats fit in it).
        push_timeout_ms: Ack timeout per profile-push attempt, 10–5000 ms.
        push_retries: Push attempts after the first, 0–10.
        segment_pace_ms: Gap between profile segments, 0–50 ms (1 ms keeps an AssistanceOff
            from queueing behind a burst: on the wire within 2.69 ms in the worst case;
            PROTOCOL.md, "Bus budget").
    """

    bus: CanBusConfig

    @property
    def heartbeat_period_s(self) -> float:
        """For :meth:`drivers.exosuit.CanEndpoint.start_heartbeat`."""
        return self.heartbeat_period_ms / 1000.0

    def push_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for :meth:`drivers.exosuit.CanEndpoint.push_profile`."""
        return {"timeout_s": self.push_timeout_ms / 1000.0, "retries": self.push_retries,
                "pace_s": self.segment_pace_ms / 1000.0}

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {
            "interface": self.bus.interface, "channel": self.bus.channel, "bitrate": self.bus.bitrate,
            "options": _jsonable(self.bus.options), "heartbeat_period_ms": self.heartbeat_period_ms,
            "push_timeout_ms": self.push_timeout_ms, "push_retries": self.push_retries,
            "segment_pace_ms": self.segment_pace_ms,
        }


def _parse_can(data: object) -> CanConfig:
    t = decode(_CanTable, data, "can", BridgeConfigError)
    allowed = INTERFACE_OPTIONS.get(t.interface)
    unknown = [k for k in t.options if allowed is not None and k not in allowed]
    if unknown:
        raise BridgeConfigError(unknown_key_message("can.options", unknown[0],
                                                    f"{t.options[unknown[0]]!r:.60}", allowed or ()))
    try:
        bus = CanBusConfig(interface=t.interface, channel=t.channel, bitrate=t.bitrate, options=t.options)
    except DriverConfigError as err:
        raise BridgeConfigError(str(err)) from err
    timing = {k: getattr(t, k) for k in _CanTiming.__struct_fields__}
    return CanConfig(bus=bus, **timing)


# --------------------------------------------------------------------------------------------
# [limits]
# --------------------------------------------------------------------------------------------

_LIMIT_DEFAULTS = ProfileLimits()
# The per-actuator limits' ranges are declared once, in bridge.safety (ACTUATOR_LIMIT_RANGES).
_LIMIT_TYPES = {k: Annotated[float, Meta(gt=lo, le=hi) if lo_open else Meta(ge=lo, le=hi)]
                for k, (lo, hi, lo_open) in ACTUATOR_LIMIT_RANGES.items()}
_ActuatorTable = msgspec.defstruct("_ActuatorTable", [(k, t | None, None) for k, t in _LIMIT_TYPES.items()],
                                   **_STRUCT)
_LimitsTable = msgspec.defstruct("_LimitsTable", [
    *((k, t, getattr(_LIMIT_DEFAULTS, k)) for k, t in _LIMIT_TYPES.items()),
    ("n_points", Annotated[int, Meta(ge=2, le=768)], _LIMIT_DEFAULTS.n_points),
    ("max_consecutive_rejections", Annotated[int, Meta(ge=1, le=100)],
     _LIMIT_DEFAULTS.max_consecutive_rejections),
    ("actuators", dict[str, Any], {}),
    ("rated_force_n", Annotated[float, Meta(gt=0.0, le=ACTUATOR_LIMIT_RANGES["max_force_n"][1])],
     RATED_FORCE_N),
], **_STRUCT)


def _parse_limits(data: object) -> ProfileLimits:
    t: Any = decode(_LimitsTable, data, "limits", BridgeConfigError)
    base = {k: getattr(t, k) for k in ACTUATOR_LIMIT_RANGES}
    base_limits = make_actuator_limits("limits", **base)  # checks the window is not empty
    _check_rating("limits", base_limits.max_force_n, t.rated_force_n)
    overrides = {}
    for name, entry in t.actuators.items():
        where = f"limits.actuators.{name}"
        o = decode(_ActuatorTable, entry, where, BridgeConfigError)
        given = {k: v for k in ACTUATOR_LIMIT_RANGES if (v := getattr(o, k)) is not None}
        overrides[name] = make_actuator_limits(where, **{**base_limits.to_json(), **given})
        _check_rating(where, overrides[name].max_force_n, t.rated_force_n)
    return ProfileLimits(**base, n_points=t.n_points, max_consecutive_rejections=t.max_consecutive_rejections,
                         actuators=overrides)


def _check_rating(where: str, max_force_n: float, rated_force_n: float) -> None:
    """A session's force limit never exceeds what the exosuit is rated for: the limit is the
    lab's to lower, the rating the device's (a stronger device raises ``rated_force_n``, once,
    knowingly), so a typo such as 5000 N cannot drive a person's actuators beyond it."""
    if max_force_n > rated_force_n:
        default = " (the default: drivers/exosuit/rating.py)" if rated_force_n == RATED_FORCE_N else ""
        raise BridgeConfigError(
            f"{where}.max_force_n = {max_force_n:g} N is above the exosuit's rated force, "
            f"limits.rated_force_n = {rated_force_n:g} N{default}; expected at most that. Lower "
            f"max_force_n, or, if your device is rated higher, set [limits] rated_force_n to its rating"
        )


# --------------------------------------------------------------------------------------------
# [watchdog]
# --------------------------------------------------------------------------------------------


class BusErrorPolicy(enum.Enum):
    """What the bridge does after a CAN bus error (assistance-off is commanded in every case).

    Only ``STOP`` is implemented: the bus's endpoint cannot be reopened within a session, so a
    bus failure ends it (the device's own heartbeat watchdog turns assistance off as well if
    the command cannot reach it), and ``hilbo run --resume`` continues the session once the bus
    is back. ``PAUSE`` (DESIGN.md's pause on a bus error) is accepted so that configs that ask
    for it load, behaves as ``STOP`` and is warned about (:func:`config_warnings`).
    """

    PAUSE = "pause"  # not implemented: behaves as STOP (see the class docstring)
    STOP = "stop"  # assistance-off, end the session (continue later with --resume)


class WatchdogConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """``[watchdog]``: when the bridge gives up on a device and commands assistance-off.

    Attributes:
        device_heartbeat_timeout_ms: No DeviceStatus for this long → assistance-off and pause,
            40–1000 ms (the device sends one every 20 ms; PROTOCOL.md uses 100 ms).
        cart_data_timeout_s: No valid breath for this long (wall clock) → assistance-off and pause;
            shorter gaps only pause estimation. 2–300 s (breaths come every 2–6 s).
        bus_error: :class:`BusErrorPolicy` (a bus failure ends the session; "pause" is not
            implemented and is warned about).
        auto_resume_s: The resume policy of headless runs (nobody to press r): a pause that the operator
            did not ask for (the pause between the bouts, a lost device heartbeat, silent cart,
            a failed push) ends by itself once the device and the cart have been healthy for
            this long (wall s, 0-3600; device faults that the bridge may clear are cleared
            first); None (the default): only the operator's ``r`` ends a pause.
            ``hilbo run --auto-resume S`` sets it, ``hilbo sim`` always uses it.
        max_auto_resumes: At most this many automatic resumes per session (1-1000); the next
            pause that would need one stops the session instead of waiting for nobody.
    """

    device_heartbeat_timeout_ms: Annotated[float, Meta(ge=40.0, le=1000.0)] = 100.0
    cart_data_timeout_s: Annotated[float, Meta(ge=2.0, le=300.0)] = 15.0
    bus_error: BusErrorPolicy = BusErrorPolicy.STOP
    auto_resume_s: Annotated[float, Meta(ge=0.0, le=3600.0)] | None = None
    max_auto_resumes: Annotated[int, Meta(ge=1, le=1000)] = 10

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return _jsonable(self)


# --------------------------------------------------------------------------------------------
# [prior]
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PriorConfig:
    """``[prior]``: fast-prior observations (Antonova 2016 §3.3), read and validated on load.

    Three sources, all optional, all entering the GP with inflated noise
    (:func:`hilbo_core.priors.inflate_variance`: ``var = factor · var_source + extra_var_w2``, per
    source, defaults :data:`hilbo_core.priors.DEFAULT_PRIOR_NOISE`, overridable in
    ``[prior.inflation.<source>]``):

    * ``observations`` — inline points: ``{params = {name = value, ...}, mean_w = W,
      var_w2 = W² (or sd_w = W), source = "short_bout" | "previous_session" | "population"}``
      (source defaults to ``short_bout``);
    * ``logs`` — previous sessions' MCAP logs of this wearer: their completed evaluations
      (``/observations``) become ``previous_session`` priors
      (:func:`hilbo_core.priors.priors_from_evaluations`);
    * ``table`` — a CSV population table (:func:`hilbo_core.priors.priors_from_rows`): a header
      row, one column per parameter of the space (by name; derived parameters may be present),
      ``mean`` (W) and ``var`` (W²) or ``sd`` (W) per row; ``subject``, ``source`` and ``note``
      columns are allowed and ignored. With ``table_baseline_w`` the table is relative: means are
      fractions of the unassisted cost (and var/sd of that fraction), scaled by it.

    Attributes:
        observations: The inline observations, validated and inflated.
        logs: The log paths, as given (relative to the working directory).
        table: The CSV path, or None.
        table_baseline_w: This wearer's unassisted cost for a relative table (W), or None.
        inflation: The inflation in effect per source (``PriorSource`` value → ``PriorNoise``).
        from_logs: The priors read from ``logs``, in log order.
        log_counts: How many priors each log gave (aligned with ``logs``).
        from_table: The priors read from ``table``.
    """

    observations: tuple[PriorObservation, ...] = ()
    logs: tuple[Path, ...] = ()
    table: Path | None = None
    table_baseline_w: float | None = None
    inflation: Mapping[str, PriorNoise] = field(
        default_factory=lambda: MappingProxyType({s.value: n for s, n in DEFAULT_PRIOR_NOISE.items()}))
    from_logs: tuple[PriorObservation, ...] = ()
    log_counts: tuple[int, ...] = ()
    from_table: tuple[PriorObservation, ...] = ()

    @property
    def priors(self) -> tuple[PriorObservation, ...]:
        """Every prior observation (inline, then logs, then table), for ``HILOptimizer``."""
        return (*self.observations, *self.from_logs, *self.from_table)

    @property
    def sources_used(self) -> tuple[str, ...]:
        """The :class:`~hilbo_core.priors.PriorSource` values of the priors present, sorted."""
        used = {p.source.split(":", 1)[0] for p in self.observations}
        if self.from_logs:
            used.add(PriorSource.PREVIOUS_SESSION.value)
        if self.from_table:
            used.add(PriorSource.POPULATION.value)
        return tuple(sorted(used))

    def event_details(self) -> dict[str, Any]:
        """What the session log's ``prior`` event records: counts by source, logs, table."""
        by_source = dict.fromkeys(self.sources_used, 0)
        for p in self.observations:
            by_source[p.source.split(":", 1)[0]] += 1
        if self.from_logs:
            by_source[PriorSource.PREVIOUS_SESSION.value] += len(self.from_logs)
        if self.from_table:
            by_source[PriorSource.POPULATION.value] += len(self.from_table)
        return {"n_priors": len(self.priors), "by_source": by_source, "n_inline": len(self.observations),
                "logs": {str(p): n for p, n in zip(self.logs, self.log_counts, strict=True)},
                "table": None if self.table is None else str(self.table), "n_table": len(self.from_table)}

    def describe(self) -> str:
        """One line: how many priors from which sources (empty config: ``none``)."""
        parts = []
        if self.observations:
            kinds = sorted({p.source.split(":", 1)[0] for p in self.observations})
            parts.append(f"{len(self.observations)} inline ({', '.join(kinds)})")
        for path, n in zip(self.logs, self.log_counts, strict=True):
            parts.append(f"{n} from log {path}")
        if self.table is not None:
            rel = f", relative to {self.table_baseline_w:g} W" if self.table_baseline_w is not None else ""
            parts.append(f"{len(self.from_table)} from table {self.table}{rel}")
        if not parts:
            return "none"
        n = len(self.priors)
        return f"{n} prior observation{'' if n == 1 else 's'}: " + "; ".join(parts)


class _Noise(msgspec.Struct, **_STRUCT):  # one [prior.inflation.<source>]; absent: the default
    factor: Annotated[float, Meta(ge=1.0, le=1e6)] | None = None
    extra_var_w2: Annotated[float, Meta(ge=0.0, le=1e8)] | None = None


_Inflation = msgspec.defstruct("_Inflation", [(s.value, _Noise | None, None) for s in PriorSource], **_STRUCT)


class _InlinePrior(msgspec.Struct, **_STRUCT):  # one entry of prior.observations
    params: dict[str, Any]
    mean_w: Annotated[float, Meta(ge=0.0, le=1e5)]
    var_w2: Annotated[float, Meta(gt=0.0, le=1e10)] | None = None
    sd_w: Annotated[float, Meta(gt=0.0, le=1e5)] | None = None
    source: PriorSource = PriorSource.SHORT_BOUT
    note: str = ""


class _PriorTable(msgspec.Struct, **_STRUCT):
    observations: Annotated[list[_InlinePrior], Meta(
        description="a list of inline tables {params = {...}, mean_w = ..., var_w2 = ...}")] = []
    logs: list[str] = []
    table: Annotated[str, Meta(min_length=1)] | None = None
    table_baseline_w: Annotated[float, Meta(gt=0.0, le=1e5)] | None = None
    inflation: _Inflation = msgspec.field(default_factory=_Inflation)  # type: ignore[valid-type]


def _prior_noise(t: _PriorTable) -> dict[str, PriorNoise]:
    noise = {s.value: n for s, n in DEFAULT_PRIOR_NOISE.items()}
    for source, base in list(noise.items()):
        if (o := getattr(t.inflation, source)) is not None:
            noise[source] = PriorNoise(
                factor=base.factor if o.factor is None else o.factor,
                extra_var_w2=base.extra_var_w2 if o.extra_var_w2 is None else o.extra_var_w2)
    return noise


def _prior_params(space: ParameterSpace, raw: Mapping[str, Any], where: str) -> dict[str, float]:
    known = (*space.names, *(d.name for d in space.derived))
    number = Annotated[float, Meta(ge=-FINITE, le=FINITE)] | None
    params = msgspec.defstruct("params", [(n, number, None) for n in known], **_STRUCT)
    given: Any = decode(params, raw, f"{where}.params", BridgeConfigError)
    values = {n: v for n in known if (v := getattr(given, n)) is not None}
    missing = [n for n in space.names if n not in values]
    if missing:
        raise BridgeConfigError(
            f"{where}.params = {dict(raw)!r:.100}: missing parameter(s) {missing}; "
            f"expected every parameter of the space: {', '.join(space.names)}"
        )
    try:
        return space.to_dict(space.check(values))
    except (ConfigError, InfeasibleError) as err:
        raise BridgeConfigError(
            f"{where}.params = {values}: outside the space ({err}); a prior must be a feasible setting"
        ) from err


def _parse_inline_prior(space: ParameterSpace, e: _InlinePrior, i: int,
                        noise: Mapping[str, PriorNoise]) -> PriorObservation:
    where = f"prior.observations[{i}]"
    params = _prior_params(space, e.params, where)
    if (e.var_w2 is None) == (e.sd_w is None):
        raise BridgeConfigError(
            f"{where}: give the uncertainty as var_w2 (W²) or sd_w (W), "
            + ("not both" if e.var_w2 is not None else "found neither")
        )
    var = e.var_w2 if e.var_w2 is not None else e.sd_w ** 2  # type: ignore[operator]
    source = e.source.value
    return PriorObservation(params, e.mean_w, inflate_variance(var, noise[source]), f"{source}:inline {i}")


def _read_prior_log(space: ParameterSpace, path: Path, i: int,
                    noise: PriorNoise) -> list[PriorObservation]:
    from bridge.log import LogError
    from bridge.log.reader import read_log

    where = f"prior.logs[{i}] = {str(path)!r}"
    if not path.is_file():
        raise BridgeConfigError(f"{where}: no such file (a previous session's .mcap log of this wearer; "
                                "paths are relative to the working directory)")
    try:
        evaluations = read_log(path, topics=["/observations"]).data("/observations")
    except (LogError, OSError) as err:
        raise BridgeConfigError(f"{where}: cannot read it as a session log: {err}") from err
    if not evaluations:
        raise BridgeConfigError(f"{where}: the log holds no completed evaluation (/observations); "
                                "remove it from prior.logs")
    try:
        return priors_from_evaluations(space, evaluations, noise=noise, label=path.name)
    except ConfigError as err:
        raise BridgeConfigError(f"{where}: {err}") from err


MAX_PRIOR_TABLE_BYTES = 16 << 20
"""Largest ``prior.table`` read (16 MiB; a population table has one short row per setting)."""


def _read_prior_table(space: ParameterSpace, path: Path, baseline_w: float | None,
                      noise: PriorNoise) -> list[PriorObservation]:
    where = f"prior.table = {str(path)!r}"
    try:
        text = read_regular_file(path, max_bytes=MAX_PRIOR_TABLE_BYTES, what="a CSV population table",
                                 error=lambda msg: BridgeConfigError(f"{where}: {msg}")).decode("utf-8-sig")
        rows = list(csv.DictReader(io.StringIO(text, newline="")))
    except FileNotFoundError as err:
        raise BridgeConfigError(f"{where}: no such file (a CSV population table; paths are relative "
                                "to the working directory)") from err
    except (OSError, UnicodeDecodeError, csv.Error) as err:
        raise BridgeConfigError(f"{where}: cannot read it as CSV: {err}") from err
    if not rows:
        raise BridgeConfigError(f"{where}: no data rows (expected a header row, then one row per setting)")
    for i, row in enumerate(rows):
        if None in row:
            raise BridgeConfigError(f"{where}: prior row {i} (line {i + 2}) has more fields than the header")
    try:
        return priors_from_rows(space, rows, noise=noise, baseline_w=baseline_w)
    except ConfigError as err:
        raise BridgeConfigError(f"{where}: {err} (rows count from 0 after the header line)") from err


def _parse_prior(data: object, space: ParameterSpace) -> PriorConfig:
    t = decode(_PriorTable, data, "prior", BridgeConfigError)
    noise = _prior_noise(t)
    observations = [_parse_inline_prior(space, e, i, noise) for i, e in enumerate(t.observations)]
    logs = tuple(Path(p) for p in t.logs)
    for i, path in enumerate(logs):
        first = next(j for j, q in enumerate(logs) if q.resolve() == path.resolve())
        if first != i:
            raise BridgeConfigError(f"prior.logs[{i}] = {str(path)!r}: the same log as prior.logs[{first}]; "
                                    "each evaluation would be counted twice")
    from_logs: list[PriorObservation] = []
    counts = []
    prev = noise[PriorSource.PREVIOUS_SESSION.value]
    for i, path in enumerate(logs):
        got = _read_prior_log(space, path, i, prev)
        from_logs += got
        counts.append(len(got))
    table = None if t.table is None else Path(t.table)
    baseline = t.table_baseline_w
    if baseline is not None and table is None:
        raise BridgeConfigError(f"prior.table_baseline_w = {baseline:g}: only with prior.table (a relative "
                                "population table)")
    from_table = [] if table is None else _read_prior_table(
        space, table, baseline, noise[PriorSource.POPULATION.value])
    return PriorConfig(
        observations=tuple(observations), logs=logs, table=table, table_baseline_w=baseline,
        inflation=MappingProxyType(noise), from_logs=tuple(from_logs), log_counts=tuple(counts),
        from_table=tuple(from_table),
    )


# --------------------------------------------------------------------------------------------
# [live]
# --------------------------------------------------------------------------------------------


class LiveConfig(msgspec.Struct, **_STRUCT):
    """``[live]``: stream the session's log channels to Foxglove while it runs (bridge/live.py).

    Attributes:
        enabled: Start the WebSocket server (``hilbo run --live`` / ``hilbo sim --live`` also do).
        host: Address to bind; ``127.0.0.1`` (this machine only) unless the lab needs another
            machine to watch: the stream is not authenticated.
        port: TCP port, 0-65535 (8765 is Foxglove's default; 0 picks a free port).
    """

    enabled: bool = False
    host: Annotated[str, Meta(min_length=1)] = "127.0.0.1"
    port: Annotated[int, Meta(ge=0, le=65535)] = 8765


class ValidationConfig(msgspec.Struct, **_STRUCT):
    """``[validation]``: the validation walk of ``hilbo validate`` (Kim et al. 2019 §IV.A.3: the
    optimised setting against a generic one and walking without assistance, 5 minutes each).

    Attributes:
        generic: The generic setting (FIX): every parameter of ``[space]`` by name, feasible;
            None: no generic condition.
        condition_min: Each condition's length in minutes of walking, 1-30 (default 5, the
            seed's); measured as ``round(condition_min · 60 / breath_interval_s)`` breaths.
        breath_interval_s: The breath interval that turns minutes into breaths, 1-10 s.
        seed: Seeds the conditions' randomised order (0 or more; one per subject counterbalances
            a study).
        zero_force: Also measure zero-force walking, the suit actuated with every force 0 N
            (bridge/validate.py: it separates the suit's own cost from its assistance's saving;
            default false).
    """

    generic: Mapping[str, float] | None = None  # checked against [space] by _parse_validation
    condition_min: Annotated[float, Meta(ge=1.0, le=30.0)] = 5.0
    breath_interval_s: Annotated[float, Meta(ge=1.0, le=10.0)] = 3.0
    seed: Annotated[int, Meta(ge=0)] = 0
    zero_force: bool = False

    @property
    def condition_breaths(self) -> int:
        """Breaths each condition is measured for."""
        return max(2, round(self.condition_min * 60.0 / self.breath_interval_s))


def _parse_validation(data: object, space: ParameterSpace) -> ValidationConfig:
    given = dict(data) if isinstance(data, Mapping) else data
    raw = given.pop("generic", None) if isinstance(given, dict) else None
    cfg = decode(ValidationConfig, given, "validation", BridgeConfigError)
    if raw is not None:
        if not isinstance(raw, Mapping):
            raise BridgeConfigError(f"validation.generic = {raw!r:.60}: expected a table such as "
                                    f"{{ {', '.join(f'{n} = ...' for n in space.names)} }}")
        missing = [n for n in space.names if n not in raw]
        unknown = [k for k in raw if k not in space.names]
        if missing or unknown:
            raise BridgeConfigError(
                f"validation.generic: expected every parameter of [space] ({', '.join(space.names)})"
                + (f"; missing {', '.join(missing)}" if missing else "")
                + (f"; unknown {', '.join(unknown)}" if unknown else ""))
        values = {}
        for k, v in raw.items():
            if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
                raise BridgeConfigError(f"validation.generic.{k} = {v!r}: expected a number")
            values[k] = float(v)
        try:
            space.check(values)
        except InfeasibleError as err:
            raise BridgeConfigError(f"validation.generic is not a feasible setting: {err}") from err
        cfg = msgspec.structs.replace(cfg, generic=MappingProxyType(values))
    return cfg


# --------------------------------------------------------------------------------------------
# The whole config
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HilboConfig:
    """A validated session config (see the module docstring for the tables).

    Attributes:
        session, space, protocol, cart, can, limits, watchdog, prior, live: The tables.
        source: Where it was read from (a path, ``<stdin>``, ``<string>``).
        text: The TOML text it was parsed from (logged, so a session can be resumed with it).
    """

    session: SessionConfig
    space: SpaceConfig
    protocol: ProtocolConfig
    cart: CartConfig
    can: CanConfig
    limits: ProfileLimits
    watchdog: WatchdogConfig
    prior: PriorConfig = field(default_factory=PriorConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    validation: ValidationConfig = field(default_factory=ValidationConfig)
    source: str = field(default="<string>", compare=False)
    text: str = field(default="", compare=False, repr=False)

    def make_gate(self) -> SafeProfileGate:
        """The limits layer for this session's space, limits and wearer."""
        return SafeProfileGate(self.space.space, self.limits, body_mass_kg=self.session.body_mass_kg)

    def to_json(self) -> dict[str, Any]:
        """JSON-able form for the log's config channel (validated values and the raw TOML)."""
        return {
            "source": self.source,
            "session": _jsonable(self.session),
            "space": self.space.to_json(),
            "protocol": self.protocol.to_json(),
            "cart": _jsonable(self.cart),
            "can": self.can.to_json(),
            "limits": self.limits.to_json(),
            "watchdog": self.watchdog.to_json(),
            "prior": _jsonable(self.prior),
            "live": _jsonable(self.live),
            "validation": _jsonable(self.validation),
            "toml": self.text,
        }


def _jsonable(obj: Any) -> Any:
    """Dataclasses, enums, paths and mappings as plain JSON values (non-finite floats as text)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, msgspec.Struct):
        return {name: _jsonable(getattr(obj, name)) for name in obj.__struct_fields__}
    if isinstance(obj, enum.Enum):
        return obj.value
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else str(float(obj))
    if isinstance(obj, str | int | bool | None):
        return obj
    return str(obj)  # TOML dates and times


_TOML_POSITION = re.compile(r"\(at line (\d+), column (\d+)\)")


def _syntax_error(err: tomllib.TOMLDecodeError, text: str, source: str) -> BridgeConfigError:
    msg = str(err)
    m = _TOML_POSITION.search(msg)
    if not m:
        return BridgeConfigError(f"{source}: TOML syntax error: {msg}")
    line, col = int(m[1]), int(m[2])
    lines = text.splitlines()
    excerpt = lines[line - 1] if 0 < line <= len(lines) else ""
    return BridgeConfigError(
        f"{source}:{line}:{col}: TOML syntax error: {msg}\n    {excerpt}\n    {' ' * (col - 1)}^"
    )


def _space_centre(space: ParameterSpace) -> dict[str, float]:
    # The mean of feasible points of a convex polytope is feasible: a deterministic interior point.
    try:
        u = space.sample_unit(64, np.random.default_rng(0)).mean(axis=0)
    except InfeasibleError as err:
        raise BridgeConfigError(f"space: {err}; widen the bounds or relax the constraints") from err
    return space.to_dict(space.from_unit(u))


def _cross_check(cfg: HilboConfig) -> None:
    space = cfg.space.space
    centre = _space_centre(space)
    try:
        probe = build_profile(space.name, centre, body_mass_kg=cfg.session.body_mass_kg)
    except (ConfigError, InfeasibleError) as err:
        raise BridgeConfigError(
            f"space: the {space.name!r} force-profile builder cannot build the centre of the space "
            f"{centre}: {err}"
        ) from err
    actuators = sorted(p.actuator for p in probe)
    for name in cfg.limits.actuators:
        if name not in actuators:
            close = difflib.get_close_matches(name, actuators, n=1, cutoff=0.6)
            hint = f" (did you mean {close[0]!r}?)" if close else ""
            raise BridgeConfigError(
                f"limits.actuators.{name}: the {space.name!r} profile has no actuator {name!r}{hint}; "
                f"its actuators: {', '.join(actuators)}"
            )
    gate = cfg.make_gate()
    verdict = gate.verdict(centre)
    if not verdict.ok:
        raise BridgeConfigError(
            f"limits: even the centre of the space ({', '.join(f'{k}={v:.4g}' for k, v in centre.items())}) "
            f"is refused: {verdict.describe()}. Widen [limits] or narrow [space]"
        )
    generic = cfg.validation.generic
    if generic is not None:
        # The validation walk's FIX passes the same gate: refused there, the walk would lose
        # its condition in front of the participant.
        verdict = gate.verdict(dict(generic))
        if not verdict.ok:
            raise BridgeConfigError(
                f"validation.generic = {{{', '.join(f'{k} = {v:g}' for k, v in generic.items())}}}: "
                f"expected a setting [limits] lets through, but it is refused: {verdict.describe()}"
            )


MAX_CONFIG_BYTES = 1 << 20
"""Largest config file read (1 MiB; the complete example config is about 10 kB)."""
MAX_CONFIG_DEPTH = 16
"""Deepest nesting of tables and arrays a config may have (the example's deepest is 4)."""


def _check_depth(data: object, source: str) -> None:
    # Iterative: the check itself must not recurse into what it bounds.
    stack: list[tuple[object, int]] = [(data, 0)]
    while stack:
        value, depth = stack.pop()
        if depth > MAX_CONFIG_DEPTH:
            raise BridgeConfigError(f"{source}: tables or arrays nested more than {MAX_CONFIG_DEPTH} "
                                    "levels deep; a config nests at most a few")
        children = value.values() if isinstance(value, dict) else value if isinstance(value, list) else ()
        stack.extend((v, depth + 1) for v in children)


def parse_config(text: str, source: str = "<string>") -> HilboConfig:
    """Parse and validate a config from TOML text.

    Args:
        text: The TOML document.
        source: Its name in error messages (a path, ``<stdin>``).

    Raises:
        BridgeConfigError: A syntax error (with line and column), a missing or unknown table or
            key, a bad type or value (naming ``table.key``, the value and what is allowed), or a
            cross-check that fails.
    """
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise _syntax_error(err, text, source) from err
    except RecursionError as err:  # arrays or inline tables nested thousands deep
        raise BridgeConfigError(f"{source}: TOML nested deeper than Python's parser can follow; a "
                                f"config nests at most {MAX_CONFIG_DEPTH} levels") from err
    _check_depth(data, source)
    for key, value in data.items():
        if key not in TABLES and not isinstance(value, dict):
            raise BridgeConfigError(
                f"{source}: top-level key {key} = {value!r:.60} outside any table; a config has only "
                f"the tables {', '.join(f'[{t}]' for t in TABLES)} (did you put it above its table header?)"
            )
        if key not in TABLES:
            raise BridgeConfigError(unknown_key_message("", key, "", TABLES))
    missing = [t for t in _REQUIRED_TABLES if t not in data]
    if missing:
        raise BridgeConfigError(
            f"{source}: missing table(s) {', '.join(f'[{t}]' for t in missing)}; "
            "`hilbo config example` prints a complete config"
        )
    session = decode(SessionConfig, data["session"], "session", BridgeConfigError)
    space = _parse_space(data["space"])
    cfg = HilboConfig(
        session=session,
        space=space,
        protocol=_parse_protocol(data.get("protocol", {})),
        cart=_parse_cart(data["cart"]),
        can=_parse_can(data["can"]),
        limits=_parse_limits(data.get("limits", {})),
        watchdog=decode(WatchdogConfig, data.get("watchdog", {}), "watchdog", BridgeConfigError),
        prior=_parse_prior(data.get("prior", {}), space.space),
        live=decode(LiveConfig, data.get("live", {}), "live", BridgeConfigError),
        validation=_parse_validation(data.get("validation", {}), space.space),
        source=source,
        text=text,
    )
    _cross_check(cfg)
    return cfg


def load_config(path: str | Path) -> HilboConfig:
    """Read and validate a config file (UTF-8 TOML).

    Raises:
        BridgeConfigError: The file cannot be read, is not a regular file or is larger than
            :data:`MAX_CONFIG_BYTES`, or see :func:`parse_config`.
    """
    path = Path(path)
    try:
        text = read_regular_file(path, max_bytes=MAX_CONFIG_BYTES, what="a TOML config",
                                 error=BridgeConfigError).decode("utf-8")
    except UnicodeDecodeError as err:
        raise BridgeConfigError(f"{path}: not UTF-8 text (TOML files are UTF-8): {err}") from err
    except OSError as err:
        raise BridgeConfigError(f"cannot read config {path}: {err.strerror or err}") from err
    return parse_config(text, source=str(path))


def check_out_dir(path: str | Path, what: str = "session.out_dir", *, create: bool = False) -> Path:
    """Refuse an output directory that cannot be created: it, or a parent, is not a directory.

    Args:
        path: The directory the session's log and summary go to (need not exist yet).
        what: How to name it in the error (``session.out_dir`` or ``--out``).
        create: Also make it now (a command about to write there): a file system that refuses
            it (``/proc``, read-only, a name too long) is said before anything starts, which the
            checks on existing parents alone cannot tell.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        BridgeConfigError: ``path`` or one of its parents exists and is not a directory, the
            nearest existing one cannot be written into, or (``create``) it cannot be made.
    """
    path = Path(path)
    if create:
        try:
            path.mkdir(parents=True, exist_ok=True)
        except (FileExistsError, NotADirectoryError):
            pass  # a file where a directory should be: the checks below name it
        except OSError as err:
            raise BridgeConfigError(f"{what} = {str(path)!r}: cannot create the output directory: "
                                    f"{err.strerror or err}") from err
    for p in (path, *path.parents):
        if p.exists():
            if not p.is_dir():
                where = "" if p == path else f" (its parent {p} is not a directory)"
                raise BridgeConfigError(
                    f"{what} = {str(path)!r}: expected a directory (existing or to be created), "
                    f"but {p} is a file{where}"
                )
            if not os.access(p, os.W_OK | os.X_OK):
                raise BridgeConfigError(
                    f"{what} = {str(path)!r}: expected a directory this user can write into, but "
                    f"{p} is not writable"
                )
            break
    return path


def config_warnings(cfg: HilboConfig) -> list[str]:
    """What is valid but probably wrong: one line each (``hilbo config check``, ``hilbo run``).

    Today: ``accept_z`` given with the accept stop off, files readable by other users
    (``session.file_mode``), a live view bound to an address other machines can reach (its
    stream is not authenticated and carries health data), and ``watchdog.bus_error = "pause"``,
    which is not implemented (:class:`BusErrorPolicy`). A force limit above the exosuit's rated force is an
    error, not a warning (``[limits] rated_force_n``).
    """
    out: list[str] = []
    pr = cfg.protocol
    if not pr.accept_stop and pr.accept_z is not None:
        out.append(f"protocol.accept_z = {pr.accept_z:g} has no effect with accept_stop = false (no "
                   "setting ends early for being better); remove one of them")
    if cfg.session.file_mode_bits & 0o077:
        out.append(f"session.file_mode = {cfg.session.file_mode!r} lets other users of this PC read the "
                   "session's files (breaths, heart rate: health data); 0600 keeps them to you")
    if cfg.watchdog.bus_error is BusErrorPolicy.PAUSE:
        out.append("watchdog.bus_error = 'pause' is not implemented yet: a CAN bus failure commands "
                   "assistance-off and ends the session; continue it with hilbo run --resume once "
                   "the bus is back (set bus_error = \"stop\" to silence this)")
    if not _is_loopback(cfg.live.host):
        out.append(f"live.host = {cfg.live.host!r} is not this machine only (127.0.0.1): with the live "
                   "view on, anyone on that network can watch the session's stream (VO2, heart rate, "
                   "forces; no authentication). Keep 127.0.0.1 unless the lab's network is trusted")
    return out


def _is_loopback(host: str) -> bool:
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def example_config_text() -> str:
    """The complete commented example config (``bridge/config_example.toml``)."""
    return resources.files("bridge").joinpath("config_example.toml").read_text(encoding="utf-8")


# --------------------------------------------------------------------------------------------
# Summary and the `hilbo config` commands
# --------------------------------------------------------------------------------------------


def _expected_end_text(pr: ProtocolConfig) -> str:
    """When the session should end, in minutes of walking after its first breath."""
    end_s = expected_end_s(pr.session_protocol_config(), breath_interval_s=DEFAULT_BREATH_INTERVAL_S)
    explore_min = pr.explore_points * pr.max_breaths * DEFAULT_BREATH_INTERVAL_S / 60.0
    if pr.session_min is not None and end_s >= 60.0 * pr.session_min:
        return (f"at the first breath past {pr.session_min:g} min of walking after the first breath "
                f"(session_min; pauses count), unless the optimisation budget is spent first")
    latest = ("" if pr.session_min is None else
              f"; at the latest at the first breath past {pr.session_min:g} min (session_min)")
    sp = pr.session_protocol_config()
    warm_ups = 2 if sp.pause_between_bouts or sp.warmup_without_pause else 1
    return (f"about {end_s / 60:.0f} min of walking after the first breath ({warm_ups} warm-up"
            f"{'s' if warm_ups > 1 else ''} of {pr.warmup_s / 60:g} min, "
            f"exploration ~{explore_min:.0f} min at "
            f"{DEFAULT_BREATH_INTERVAL_S:g} s per breath, then the optimisation budget"
            f"{', plus the pause between the bouts' if pr.pauses_between_bouts else ''}){latest}")


def _sound_text(pr: ProtocolConfig) -> str:
    """The sound rule's constants for the summary ("" for Kim et al. 2019's rules)."""
    if not pr.stopping.is_sound:
        return ""
    opt = pr.optimizer_config(with_budget=False)
    z = pr.accept_margin_z
    accept = "no accept stop" if z is None else f"accept at {z:g} σ"
    if pr.stopping is StoppingKind.SOUND:
        return (f"; no decision before {opt.min_decision_s:g} s, sequential boundaries until "
                f"{opt.boundary_s:g} s, then reject above {opt.a_floor:g} σ at least, {accept}")
    return f"; no decision before {opt.min_decision_s:g} s, reject above {opt.a_floor:g} σ at least, {accept}"


def summarize(cfg: HilboConfig) -> str:
    """A few lines saying what the config will do."""
    s, sp, pr, c, lim, wd = cfg.session, cfg.space.space, cfg.protocol, cfg.can, cfg.limits, cfg.watchdog
    params = ", ".join(f"{p.name} [{p.lower:g}, {p.upper:g}]{' ' + p.unit if p.unit else ''}"
                       for p in sp.parameters)
    origin = f"preset {cfg.space.preset}" if cfg.space.preset else f"inline, profile {sp.name}"
    budget = " and ".join(
        b for b in (f"{pr.budget_min:g} min" if pr.budget_min is not None else "",
                    f"{pr.budget_breaths} breaths" if pr.budget_breaths is not None else "") if b
    )
    lines = [
        f"session   subject {s.subject}, {s.body_mass_kg:g} kg, output in {s.out_dir}"
        + ("" if s.out_dir.is_absolute() else f" ({s.out_dir.resolve()})"),
        f"space     {origin}: {params}",
        f"          constraints: {'; '.join(k.describe() for k in sp.constraints) or 'none'}"
        + (f"; derived: {'; '.join(d.text or d.name for d in sp.derived)}" if sp.derived else ""),
        f"protocol  {pr.protocol_kind.value}: warm-up {pr.warmup_s:g} s"
        f"{'' if pr.session_protocol_config().warmup_without_pause or pr.pauses_between_bouts else ' (once)'}"
        f"; exploration {pr.explore_points} settings x "
        f"{pr.max_breaths} breaths ({DesignKind(pr.optimizer_config().design).value} design); "
        f"optimisation budget {budget}; {pr.stopping.value} stopping "
        f"(W = {pr.window}{_sound_text(pr)}); {pr.kernel.value} kernel, GP prior mean "
        f"+{pr.optimizer_config().prior_mean_sd:g} SD, xi = {pr.xi:g}, seed {pr.seed}; "
        f"{'pause' if pr.pauses_between_bouts else 'no pause'} between bouts; "
        + (f"the last {pr.session_protocol_config().confirm_s / 60:g} min confirm the recommendation"
           if pr.session_protocol_config().confirm_s else "no confirmation"),
        "          after a pause: "
        + (f"up to {pr.short_pause_s:g} s the same setting again at once, longer ones a warm-up "
           "first" if pr.short_pause_s > 0 else "a warm-up first, then the same setting again"),
        f"          expected end {_expected_end_text(pr)}",
        f"cart      {cfg.cart.transport}, {cfg.cart.format.value}",
        f"can       {c.bus.interface}:{c.bus.channel}, bitrate {c.bus.bitrate}, heartbeat "
        f"{c.heartbeat_period_ms:g} ms, push timeout {c.push_timeout_ms:g} ms x "
        f"{c.push_retries + 1} attempts, segments every {c.segment_pace_ms:g} ms",
    ]
    for name, a in [("(all)", lim.default), *lim.actuators.items()]:
        lines.append(
            f"limits    {name}: force <= {a.max_force_n:g} N within [{a.min_onset_pct:g}, "
            f"{a.max_offset_pct:g}] %GC, slope <= {a.max_slope_n_per_pct:g} N/%GC, peak step <= "
            f"{a.max_peak_change_n:g} N"
        )
    lines.append(f"          {lim.n_points}-point tables; pause after {lim.max_consecutive_rejections} "
                 "rejected proposals in a row")
    lines.append(f"watchdog  device heartbeat {wd.device_heartbeat_timeout_ms:g} ms, cart data "
                 f"{wd.cart_data_timeout_s:g} s, bus error -> assistance-off and the session ends")
    lines.append(f"prior     {cfg.prior.describe()}")
    lines.append(f"validate  {_describe_validation(cfg)}")
    if cfg.live.enabled:
        lines.append(f"live      Foxglove WebSocket on ws://{cfg.live.host}:{cfg.live.port}")
    if cfg.prior.priors:
        lines.append("          inflation (var x factor + extra): " + "; ".join(
            f"{k} x {cfg.prior.inflation[k].factor:g} + {cfg.prior.inflation[k].extra_var_w2:g} W²"
            for k in cfg.prior.sources_used))
    return "\n".join(lines)


def _describe_validation(cfg: HilboConfig) -> str:
    """What ``hilbo validate`` with this config measures (``[validation]``)."""
    v = cfg.validation
    names = ["OPT (the session's recommendation)"]
    if v.generic is not None:
        names.append(f"FIX ({format_params(v.generic, cfg.space.space.units)})")
    names.append("unassisted")
    if v.zero_force:
        names.append("zero-force")
    text = (f"hilbo validate: {', '.join(names)}; {v.condition_min:g} min ({v.condition_breaths} "
            f"breaths) each, in an order seeded by {v.seed}")
    if v.generic is None:
        text += " (no [validation] generic: OPT against unassisted walking only)"
    return text


def _cmd_example(args: argparse.Namespace, out: TextIO | None = None) -> int:
    (out or sys.stdout).write(example_config_text())
    return 0


def _cmd_check(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    out = out or sys.stdout
    err = err or sys.stderr
    try:
        if args.config == "-":
            cfg = parse_config(sys.stdin.read(), source="<stdin>")
        else:
            cfg = load_config(args.config)
        check_out_dir(cfg.session.out_dir)
    except BridgeConfigError as exc:
        err.write(f"hilbo config check: invalid config: {exc}\n")
        return 1
    # The cart file is part of the config: "config OK" only once it has been read as the
    # session would read it.
    cart = io.StringIO()
    if check_cart_file(cfg, cart, err) != 0:
        out.write(cart.getvalue())
        return 1
    out.write(f"config OK: {cfg.source}\n{summarize(cfg)}\n{cart.getvalue()}")
    for warning in config_warnings(cfg):
        err.write(f"hilbo config check: warning: {warning}\n")
    if args.samples > 0:
        report = preflight(cfg.space.space, cfg.limits, body_mass_kg=cfg.session.body_mass_kg,
                           n=args.samples)
        kinds = ", ".join(f"{k} {n}" for k, n in sorted(report.by_kind.items()))
        out.write(f"pre-flight {report.n_checked} sampled settings: {report.n_rejected} refused by the "
                  f"limits{f' ({kinds})' if kinds else ''}\n")
        if report.n_rejected == report.n_checked:
            err.write(f"hilbo config check: the limits refuse every sampled setting, e.g. "
                      f"{report.example}\n")
            return 1
        if report.n_rejected:
            err.write(f"hilbo config check: warning: {report.n_rejected} of {report.n_checked} "
                      f"settings would be refused (each refusal cancels the setting), e.g. "
                      f"{report.example}\n")
    return 0


def check_cart_file(cfg: HilboConfig, out: TextIO, err: TextIO, prog: str = "hilbo config check") -> int:
    """A replay config: open the file as the session would; show its first records and rejects.

    Returns:
        0 when the file is usable (or the cart is not a file), else 1 after one line on ``err``
        that starts with ``prog``.
    """
    from drivers.cart.inspect import inspect_config

    try:
        report = inspect_config(cfg.cart)
    except DriverConfigError as exc:
        err.write(f"{prog}: [cart] file does not fit the config: {exc}\n")
        return 1
    except OSError as exc:
        err.write(f"{prog}: cannot read cart.options.path {cfg.cart.options.path}: "
                  f"{exc.strerror or exc}\n")
        return 1
    if report is None:
        return 0
    from drivers.cart.errors import CartError
    from drivers.cart.pipeline import SPACING_BREATHS, check_breath_spacing

    try:
        check_breath_spacing([r.t_s for r in report.records[:SPACING_BREATHS]],
                             source=f"cart file {report.path}")
    except CartError as exc:
        err.write(f"{prog}: {exc}\n")
        return 1
    by_reason = ", ".join(f"{k} {v}" for k, v in report.rejects.most_common())
    out.write(f"cart file {report.path}: {len(report.records)} breaths read, {report.n_rejected} "
              f"rejected{f' ({by_reason})' if by_reason else ''}\n")
    for rec in report.records[:3]:
        out.write(f"          {describe_record(rec)}\n")
    for reason, examples in report.reject_examples.items():
        out.write(f"          reject {reason}: {examples[0]}\n")
    if not report.records:
        err.write(f"{prog}: every record of {report.path} is rejected; check [cart] "
                  "format and the [cart.csv] units and time format\n")
        return 1
    return 0


def add_config_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``hilbo config example`` and ``hilbo config check CONFIG.toml``.

    Args:
        subparsers: The ``add_subparsers()`` object of the ``hilbo`` parser.

    Returns:
        The ``config`` parser. Each action sets ``func(args) -> exit code`` (0 ok, 1 invalid;
        argparse's 2 is for a wrong command line).
    """
    parser = subparsers.add_parser(
        "config", help="print an example session config, or check one",
        description="Session configs are TOML files; `example` prints a complete commented one, "
                    "`check` validates one and prints what it will do.",
    )
    actions = parser.add_subparsers(dest="config_action", required=True, metavar="ACTION")
    example = actions.add_parser("example", help="print a complete commented config",
                                 description="Print a complete commented config to standard output.")
    example.set_defaults(func=_cmd_example)
    check = actions.add_parser(
        "check", help="validate a config and print a summary (exit 0 ok, 1 invalid)",
        description="Validate a config, print a summary, and check how many sampled settings of "
                    "the space the limits refuse. Exit status 0 if valid, 1 if not.",
    )
    check.add_argument("config", help="CONFIG.toml, or - to read standard input")
    check.add_argument("--samples", type=nonnegative_int, default=256,
                       help="settings to sample for the limits pre-flight (default 256; 0 skips it)")
    check.set_defaults(func=_cmd_check)
    return parser


#: The keys each table allows (``[cart]``'s are the cart driver's: drivers/cart/FORMAT.md).
ALLOWED_KEYS: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "session": SessionConfig.__struct_fields__,
    "space": _SpaceTable.__struct_fields__,
    "protocol": ProtocolConfig.__struct_fields__,
    "can": _CanTable.__struct_fields__,
    "limits": _LimitsTable.__struct_fields__,
    "watchdog": WatchdogConfig.__struct_fields__,
    "prior": _PriorTable.__struct_fields__,
    "live": LiveConfig.__struct_fields__,
    "validation": ValidationConfig.__struct_fields__,
})
