"""``hilbo validate``: the validation walk after an optimisation (Kim et al. 2019 §IV.A.3).

The seed's human study measured walking "with and without the exosuit" for 5 minutes each,
with the individually optimised parameters (OPT) and fixed generic ones (FIX), and reports each
assisted condition's reduction against walking without assistance. Here:

* the **conditions**: the session's recommended setting (read from its log through the
  optimizer's own recommendation, :meth:`HILOptimizer.best`), the generic setting of
  ``[validation] generic``, unassisted walking (assistance off, the suit worn), and, with
  ``[validation] zero_force = true``, zero-force walking (below);
* their **order** is randomised with ``[validation] seed`` (one seed per subject
  counterbalances a study), after the protocol's unassisted warm-up;
* each is measured for ``[validation] condition_min`` minutes of walking (as breaths) with the
  session's own estimator, from the level the previous condition left the body at (the
  estimator models that transition: shared/DESIGN.md, "Metabolic estimation");
* the measurement is a :class:`~bridge.runtime.BridgeSession` like ``hilbo run``'s, through
  :func:`bridge.run.run_session` (the same safety gate, pauses, resume policy, log and operator
  view): the conditions are the exploration design of an optimizer that measures every setting
  for the same number of breaths, and a gate (:class:`ConditionGate`) turns the unassisted
  condition into "assistance off" instead of a profile. A pause abandons the condition being
  measured and re-measures the same one.

**Zero force is not unassisted.** Unassisted here is assistance off: the device ramps to slack
and follows no table, its force controller idle. Zero force is the suit worn and *actuated*
with a profile of 0 N at every point, pushed like any other through the same safety gate
(:meth:`SafeProfileGate.admit_zero_force`; drivers/PROTOCOL.md has no separate command for the
transparent mode, and an all-zero table is within every limit), so the force controller runs
and tracks zero force: the wearer feels the suit's mass and whatever force the tracking leaves
(its error, friction and inertia of the drive it does not cancel), and no assistance. The
exosuit literature separates the suit's own cost from what its assistance saves this way: Kim
et al. 2019's multi-joint study reports its reductions against a slack (powered-off) suit as
well as against no suit (its Table II). The zero-force condition's reduction against unassisted
walking is that cost of the running suit (expected at or below 0 on a person); the simulated
wearers of ``virtual_hw`` model no mass, friction or tracking error, so for them a zero table is
unassisted walking exactly and the true reduction is 0.

The result per condition (estimate, 95 % interval, reduction against unassisted with its 95 %
interval by the delta method) goes into the summary and the log (a ``validation_result``
event that ``hilbo review`` reports).
"""

from __future__ import annotations

import dataclasses
import enum
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bridge.config import HilboConfig
from bridge.errors import BridgeError
from bridge.log.reader import read_log
from bridge.log.resume import rebuild_optimizer
from bridge.outcome import Z95, SessionEnd, format_params
from bridge.runtime import BridgeSession
from bridge.safety import AdmittedProfile, SafeProfileGate
from hilbo_core import HILOptimizer
from hilbo_core.protocol import SessionProtocol
from hilbo_core.space import ParameterSpace

__all__ = [
    "Condition",
    "ConditionGate",
    "ConditionKind",
    "ValidationError",
    "ValidationPlan",
    "condition_results",
    "plan_conditions",
    "plan_event",
    "recommended_setting",
]


class ValidationError(BridgeError):
    """``hilbo validate`` cannot run as asked (names what is missing)."""


class ConditionKind(enum.Enum):
    """What a validation condition is."""

    RECOMMENDED = "recommended"  # OPT: the session's recommended setting
    GENERIC = "generic"  # FIX: [validation] generic
    UNASSISTED = "unassisted"  # assistance off, the suit worn
    ZERO_FORCE = "zero_force"  # the suit actuated, tracking 0 N (module docstring)


_NAMES = {ConditionKind.RECOMMENDED: "OPT", ConditionKind.GENERIC: "FIX",
          ConditionKind.UNASSISTED: "unassisted", ConditionKind.ZERO_FORCE: "zero-force"}
# What the conditions without a setting of their own do, for the text.
_WITHOUT_SETTING = {ConditionKind.UNASSISTED: "assistance off",
                    ConditionKind.ZERO_FORCE: "zero force (suit actuated, 0 N at every point)"}


@dataclasses.dataclass(frozen=True)
class Condition:
    """One condition of the validation walk.

    Attributes:
        name: ``OPT``, ``FIX``, ``unassisted`` or ``zero-force``.
        kind: :class:`ConditionKind`.
        params: The setting; for unassisted and zero-force walking, the setting the optimizer
            records for it (the recommended one: for unassisted nothing of it reaches the device;
            for zero force only its tables' actuators and grid do, every force 0 N).
    """

    name: str
    kind: ConditionKind
    params: Mapping[str, float]

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (the log's ``validation_plan`` event)."""
        return {"name": self.name, "kind": self.kind.value, "params": dict(self.params)}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> Condition:
        """The inverse of :meth:`to_json`."""
        return cls(str(data["name"]), ConditionKind(data["kind"]),
                   {k: float(v) for k, v in data["params"].items()})


def recommended_setting(log: Path) -> tuple[dict[str, float], float, float]:
    """The recommended setting of the session in ``log`` and its estimate ``(params, mean_w,
    var_w2)``: :meth:`HILOptimizer.best` of the optimizer rebuilt from the log."""
    opt, _ = rebuild_optimizer(log)
    if not opt.evaluations:
        raise ValidationError(f"{log}: the session completed no evaluation; nothing to validate")
    params, mean, var = opt.best()
    return dict(params), float(mean), float(var)


def plan_conditions(recommended: Mapping[str, float], generic: Mapping[str, float] | None,
                    seed: int, *, zero_force: bool = False) -> list[Condition]:
    """The conditions in their randomised order (``np.random.default_rng(seed)``).

    Args:
        recommended: OPT's setting.
        generic: FIX's setting, or None for no FIX.
        seed: Seeds the order.
        zero_force: Include the zero-force condition (module docstring).
    """
    opt = ConditionKind.RECOMMENDED
    conditions = [Condition(_NAMES[opt], opt, dict(recommended))]
    if generic is not None:
        conditions.append(Condition(_NAMES[ConditionKind.GENERIC], ConditionKind.GENERIC, dict(generic)))
    without = [ConditionKind.UNASSISTED] + ([ConditionKind.ZERO_FORCE] if zero_force else [])
    conditions += [Condition(_NAMES[kind], kind, dict(recommended)) for kind in without]
    order = np.random.default_rng(seed).permutation(len(conditions))
    return [conditions[int(k)] for k in order]


class ConditionGate:
    """The session's gate for the validation walk: the assisted conditions pass the safety gate
    as in ``hilbo run``; the unassisted one is ``None`` (assistance off, nothing pushed); the
    zero-force one is the gate's all-zero tables (:meth:`SafeProfileGate.admit_zero_force`).

    Args:
        gate: The config's safety gate.
        conditions: The plan, in measuring order.
        current: The index of the condition being proposed (the optimizer's evaluations so far).
    """

    def __init__(self, gate: SafeProfileGate, conditions: Sequence[Condition],
                 current: Callable[[], int]) -> None:
        self.gate = gate
        self.conditions = list(conditions)
        self.current = current

    def admit(self, params: dict[str, float]) -> AdmittedProfile | None:
        """The safety gate's verdict, or None for the unassisted condition."""
        kind = self.conditions[self.current()].kind
        if kind is ConditionKind.UNASSISTED:
            return None
        if kind is ConditionKind.ZERO_FORCE:
            return self.gate.admit_zero_force(params)
        return self.gate.admit(params)

    def acknowledge(self, admitted: AdmittedProfile) -> None:
        """As :meth:`SafeProfileGate.acknowledge`."""
        self.gate.acknowledge(admitted)

    def assistance_off(self) -> None:
        """As :meth:`SafeProfileGate.assistance_off`."""
        self.gate.assistance_off()

    @property
    def rejections_exhausted(self) -> bool:
        """As :attr:`SafeProfileGate.rejections_exhausted`."""
        return self.gate.rejections_exhausted


def _optimizer(cfg: HilboConfig, conditions: Sequence[Condition]) -> HILOptimizer:
    """An optimizer whose exploration design is the conditions, each measured for the same
    number of breaths: the session machinery measures them as it measures exploration points."""
    space: ParameterSpace = cfg.space.space
    config = dataclasses.replace(cfg.protocol.optimizer_config(with_budget=False),
                                 n_explore=len(conditions), max_breaths=cfg.validation.condition_breaths)
    state = HILOptimizer(space, config=config).to_json()
    state["design"] = [space.check(c.params).tolist() for c in conditions]
    return HILOptimizer.from_json(state)


def _protocol(cfg: HilboConfig, n: int, *, resumed_evaluations: int | None = None) -> SessionProtocol:
    # The conditions are the exploration bout; the session ends after its last one (attach()).
    # The protocol's own ends are back-stops only: the first breath of an optimisation bout,
    # and a walking time three times the plan's, plus half an hour for pauses.
    v = cfg.validation
    config = dataclasses.replace(
        cfg.protocol.session_protocol_config(), n_explore=n, max_breaths=v.condition_breaths,
        session_s=cfg.protocol.warmup_s + 3 * n * v.condition_min * 60.0 + 1800.0,
        budget_s=None, budget_breaths=1, pause_between_bouts=False, confirm_s=None)
    if resumed_evaluations is None:
        return SessionProtocol(config)
    return SessionProtocol.resumed(config, n_explored=resumed_evaluations)


def plan_event(events: Sequence[Any]) -> Any | None:
    """The ``validation_plan`` event among a log's ``/events`` records, or None.

    Every validation walk's log has one (:meth:`ValidationPlan.attach` writes it as the walk
    starts); an optimisation session's log has none.
    """
    return next((e for e in events if getattr(e, "kind", None) == "validation_plan"), None)


def _plan_from_log(log: Path) -> tuple[list[Condition], str | None]:
    """The conditions of a validation log (its ``validation_plan`` event) and its source log."""
    plan = plan_event(read_log(log, topics=["/events"]).records("/events"))
    if plan is None or not plan.details:
        raise ValidationError(f"{log} is not a validation walk's log (no validation_plan event); "
                              "resume a hilbo run session with hilbo run --resume")
    return [Condition.from_json(c) for c in plan.details["conditions"]], plan.details.get("source_log")


def condition_results(conditions: Sequence[Condition], records: Sequence[Mapping[str, Any]],
                      units: Mapping[str, str] | None = None) -> list[dict[str, Any]]:
    """Each condition's estimate with its 95 % interval, and its reduction against unassisted.

    The reduction is ``1 - c / c_unassisted``; its interval by the delta method on the two
    independent estimates: ``var(r) ≈ (c/c_u)² (var_c/c² + var_u/c_u²)``.

    Args:
        conditions: The plan, in measuring order.
        records: The session's completed evaluations (``BridgeSession.records``: ``index``,
            ``mean``, ``var``, ``breaths``, ``t_start``, ``t_end``).
        units: Parameter units, for the text.
    """
    by_index = {int(r["index"]): r for r in records}
    unassisted = next((by_index.get(k) for k, c in enumerate(conditions)
                       if c.kind is ConditionKind.UNASSISTED), None)
    out = []
    for k, c in enumerate(conditions):
        r = by_index.get(k)
        row: dict[str, Any] = {"order": k + 1, **c.to_json(), "measured": r is not None}
        if c.kind in _WITHOUT_SETTING:
            row["params"] = None
            row["setting"] = _WITHOUT_SETTING[c.kind]
        else:
            row["setting"] = format_params(c.params, units or {})
        if r is not None:
            mean, var = float(r["mean"]), float(r["var"])
            sd = math.sqrt(max(var, 0.0))
            row.update(mean_w=mean, var_w2=var, ci95_w=[mean - Z95 * sd, mean + Z95 * sd],
                       breaths=int(r["breaths"]), t_start_s=r.get("t_start"), t_end_s=r.get("t_end"))
            if unassisted is not None and c.kind is not ConditionKind.UNASSISTED:
                cu, vu = float(unassisted["mean"]), float(unassisted["var"])
                ratio = mean / cu
                sd_r = abs(ratio) * math.sqrt(var / mean**2 + vu / cu**2)
                red = 1.0 - ratio
                row.update(reduction=red, reduction_ci95=[red - Z95 * sd_r, red + Z95 * sd_r])
        out.append(row)
    return out


def result_lines(results: Sequence[Mapping[str, Any]]) -> list[str]:
    """One line per condition for the terminal."""
    lines = []
    for r in results:
        head = f"{r['order']}. {r['name']:10s}"
        if not r["measured"]:
            lines.append(f"{head} not measured")
            continue
        lo, hi = r["ci95_w"]
        text = f"{head} {r['mean_w']:.1f} W (95 % CI {lo:.1f} to {hi:.1f} W, {r['breaths']} breaths)"
        if "reduction" in r:
            rlo, rhi = r["reduction_ci95"]
            text += (f"; reduction against unassisted {100 * r['reduction']:.1f} % "
                     f"(95 % CI {100 * rlo:.1f} to {100 * rhi:.1f} %)")
        if r.get("setting"):
            text += f"; {r['setting']}"
        lines.append(text)
    return lines


@dataclasses.dataclass
class ValidationPlan:
    """What :func:`bridge.run.run_session` needs to run the validation walk instead of an
    optimisation: the optimizer and protocol that measure the conditions, the gate, the hook
    that ends the session after the last condition, and the summary's results.

    Build it with :meth:`new` (from an optimisation session's log) or :meth:`resumed` (from a
    validation log cut off by a crash or a stop).
    """

    conditions: list[Condition]
    source_log: str | None
    optimizer: HILOptimizer
    protocol: SessionProtocol
    units: dict[str, str]

    @classmethod
    def new(cls, cfg: HilboConfig, source_log: Path) -> ValidationPlan:
        """The plan for the session of ``source_log`` (its recommendation) and ``cfg``.

        Raises:
            ValidationError: ``source_log`` is a validation walk's log, not an optimisation
                session's (a walk recommends nothing; its optimizer only measured conditions).
        """
        walk = plan_event(read_log(source_log, topics=["/events"]).records("/events"))
        if walk is not None:
            validated = (walk.details or {}).get("source_log")
            raise ValidationError(
                f"{source_log} is a validation walk's log (hilbo validate); --from takes the "
                "optimisation session's log" + (f" (this walk validated {validated})" if validated else ""))
        params, _, _ = recommended_setting(source_log)
        cfg.space.space.check(params)
        conditions = plan_conditions(params, cfg.validation.generic, cfg.validation.seed,
                                     zero_force=cfg.validation.zero_force)
        return cls(conditions, str(source_log), _optimizer(cfg, conditions),
                   _protocol(cfg, len(conditions)), cfg.space.space.units)

    @classmethod
    def resumed(cls, cfg: HilboConfig, log: Path) -> ValidationPlan:
        """The plan of a validation log, continued: the conditions measured stay measured."""
        conditions, source = _plan_from_log(log)
        opt, _ = rebuild_optimizer(log)
        done = len(opt.evaluations)
        if done >= len(conditions):
            raise ValidationError(f"{log}: every condition of this validation walk was measured; "
                                  "there is nothing to resume")
        return cls(conditions, source, opt, _protocol(cfg, len(conditions), resumed_evaluations=done),
                   cfg.space.space.units)

    def gate(self, gate: SafeProfileGate, session: Callable[[], BridgeSession]) -> ConditionGate:
        """The session's gate (``session`` returns the session once it exists)."""
        return ConditionGate(gate, self.conditions, lambda: min(len(session().opt.evaluations),
                                                                len(self.conditions) - 1))

    def attach(self, session: BridgeSession) -> None:
        """Log the plan and end the session once every condition is measured."""
        session.log.log_event("validation_plan", "validation walk: " + ", ".join(
            f"{k + 1}. {c.name}" for k, c in enumerate(self.conditions)),
            conditions=[c.to_json() for c in self.conditions], source_log=self.source_log)
        # The session ends the moment the last condition's evaluation completes: nothing is
        # asked or pushed after it (an optimisation proposal must never reach the wearer here).
        session.end_after = (len(self.conditions), SessionEnd.CONDITIONS_DONE)
        session.evaluation_name = lambda k: getattr(self._condition(k), "name", "?")

    def _condition(self, index: int) -> Condition | None:
        """The condition evaluation ``index`` measures (None past the plan)."""
        return self.conditions[index] if 0 <= index < len(self.conditions) else None

    def label_summary(self, summary: dict[str, Any]) -> None:
        """A walk's ``summary.json``: each evaluation names the condition it measured (and, for
        unassisted and zero-force walking, carries no setting: the optimizer records OPT's for
        them, :class:`Condition`), and there is no recommendation (a GP over fixed conditions
        recommends nothing; OPT is the recommendation of ``validated_log``)."""
        for r in summary.get("evaluations") or ():
            c = self._condition(int(r["index"]))
            if c is not None:
                r["condition"] = c.name
                if c.kind in _WITHOUT_SETTING:
                    r["params"], r["setting"] = None, _WITHOUT_SETTING[c.kind]
        summary.update(best_params=None, best_mean=None, best_var=None, recommendation=None,
                       confirmation=None, validated_log=self.source_log)

    def results(self, session: BridgeSession) -> list[dict[str, Any]]:
        """The per-condition results; logged as the ``validation_result`` event."""
        records = [{**e.to_json(), "index": k} for k, e in enumerate(session.opt.evaluations)]
        times = {int(r["index"]): r for r in session.records}
        for r in records:
            r.update({k: times[r["index"]][k] for k in ("t_start", "t_end") if r["index"] in times})
        results = condition_results(self.conditions, records, self.units)
        session.log.log_event("validation_result", "; ".join(result_lines(results)),
                              conditions=results, source_log=self.source_log)
        return results
