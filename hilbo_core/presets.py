"""Parameter-space presets of Kim et al. 2019's two human studies (Kim et al. 2019 §IV.A.2 and §IV.B.2)."""

from __future__ import annotations

from hilbo_core.space import Parameter, ParameterSpace

__all__ = ["PRESETS", "hip_6d", "hip_ankle_4d", "preset"]


def hip_6d() -> ParameterSpace:
    """Single-joint hip-extension assistance, six parameters (Kim et al. 2019 §IV.A.2, Fig. 3a).

    Parameters: onset ``t_on``, peak ``t_p`` and offset ``t_off`` timings in % of the gait cycle
    (from maximum hip flexion, %GC_MHF), peak force ``F_p`` in N, and the rising and falling
    node forces ``F_r``, ``F_f`` as ratios of ``F_p`` (the nodes sit midway through the rising
    and falling phases). Constraints, as printed in Kim et al. 2019::

        0 <= t_on <= t_p - 15,   t_p + 15 <= t_off <= 55,   50 N <= F_p <= 250 N,
        0.3 F_p <= F_r <= 0.7 F_p,   0.3 F_p <= F_f <= 0.7 F_p

    Expressing the nodes as ratios turns the last two constraints into plain bounds [0.3, 0.7];
    the box bounds of the timings are the tightest the linear constraints allow.
    """
    return ParameterSpace(
        [
            Parameter("t_on", 0.0, 25.0, "%GC", "assistance onset timing"),
            Parameter("t_p", 15.0, 40.0, "%GC", "peak force timing"),
            Parameter("t_off", 30.0, 55.0, "%GC", "assistance offset timing"),
            Parameter("F_p", 50.0, 250.0, "N", "peak force"),
            Parameter("F_r", 0.3, 0.7, "ratio of F_p", "rising node force"),
            Parameter("F_f", 0.3, 0.7, "ratio of F_p", "falling node force"),
        ],
        constraints=["t_on <= t_p - 15", "t_p + 15 <= t_off"],
        name="hip_6d",
    )


def hip_ankle_4d() -> ParameterSpace:
    """Multi-joint hip + ankle assistance, four parameters (Kim et al. 2019 §IV.B.2, Fig. 3b).

    Hip extension: peak timing ``hip_t_peak`` in [15, 50] %GC_MHF and offset timing
    ``hip_t_offset`` in [30, 65] %GC_MHF (peak force fixed at 40 % body weight). Ankle
    plantarflexion: cable-retraction onset ``ankle_t1`` in [30, 40] %GC_HS and completion
    ``ankle_t2`` in [50, 60] %GC_HS with ``ankle_t1 + 10 <= ankle_t2``; the release onset is the
    derived ``ankle_t3 = ankle_t2 + 10`` (peak force 60 % body weight).

    Deliberate difference from Kim et al. 2019: it prints the hip constraint as
    ``T_offset + 15 <= T_peak``. With the bounds above that leaves only a sliver
    (T_peak >= 45, T_offset <= 35) and contradicts its own Table II (peak 21-26 %, offset
    41-45 %), so this preset uses ``hip_t_peak + 15 <= hip_t_offset`` (shared/DESIGN.md).
    """
    return ParameterSpace(
        [
            Parameter("hip_t_peak", 15.0, 50.0, "%GC", "hip peak force timing"),
            Parameter("hip_t_offset", 30.0, 65.0, "%GC", "hip assistance offset timing"),
            Parameter("ankle_t1", 30.0, 40.0, "%GC", "ankle cable-retraction onset"),
            Parameter("ankle_t2", 50.0, 60.0, "%GC", "ankle cable-retraction completion"),
        ],
        constraints=["hip_t_peak + 15 <= hip_t_offset", "ankle_t1 + 10 <= ankle_t2"],
        derived=["ankle_t3 = ankle_t2 + 10"],
        name="hip_ankle_4d",
    )


PRESETS = {"hip_6d": hip_6d, "hip_ankle_4d": hip_ankle_4d}


def preset(name: str) -> ParameterSpace:
    """A preset space by name (``"hip_6d"`` or ``"hip_ankle_4d"``)."""
    from hilbo_core.errors import ConfigError

    try:
        return PRESETS[name]()
    except KeyError as err:
        raise ConfigError(
            f"unknown parameter-space preset {name!r}; choose one of {sorted(PRESETS)}"
        ) from err
