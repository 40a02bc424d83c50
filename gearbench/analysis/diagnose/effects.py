"""The candidate library: effects the paper's model ``J th'' + D th' + C th = Kt i`` lacks.

Each effect is one small class (see base.Effect), grouped by kind: friction.py,
periodic.py (cogging, ripple, position-dependent load torque), current.py (offset,
delay, saturation, inertia, encoder), mechanics.py (shaft, backlash).

Vocabulary: coulomb_friction, stribeck_friction, direction_friction,
position_friction, presliding_friction, cogging, torque_ripple, load_torque,
current_offset, time_delay, kt_saturation, shaft_compliance, backlash,
encoder_quantization, inertia_mismatch.
"""
from __future__ import annotations

from .base import MIN_SUPPORT, Base, Effect, split_timing
from .current import (ConstantTerm, CurrentOffset, EncoderQuantization,
                      InertiaMismatch, KtSaturation, TimeDelay)
from .friction import (CoulombFriction, CoulombTerm, DahlTerm, DirectionFriction,
                       DirectionTerm, FrictionTerm, PositionFriction, PositionFrictionTerm,
                       PreslidingFriction, StribeckFriction, StribeckTerm, _dahl_track,
                       mean_abs_tanh, mean_tanh, speed_scale)
from .mechanics import (Backlash, DiskTerm, RigidGapTerm, ShaftCompliance,
                        _disk_track, _gap_track, two_mass_step)
from .periodic import (Cogging, CoggingTerm, LoadTorque, LoadTorqueTerm, RippleTerm,
                       TorqueRipple)

LIBRARY: tuple[Effect, ...] = (
    CoulombFriction(), StribeckFriction(), DirectionFriction(), PositionFriction(),
    PreslidingFriction(), Cogging(), TorqueRipple(), LoadTorque(), CurrentOffset(),
    TimeDelay(), KtSaturation(), ShaftCompliance(), Backlash(), EncoderQuantization(),
    InertiaMismatch(),
)
NAMES = tuple(e.name for e in LIBRARY)

__all__ = ["LIBRARY", "NAMES", "MIN_SUPPORT", "Base", "Effect", "split_timing", "ConstantTerm",
           "CurrentOffset", "EncoderQuantization", "InertiaMismatch", "KtSaturation",
           "TimeDelay", "CoulombFriction", "CoulombTerm", "DahlTerm", "DirectionFriction",
           "DirectionTerm", "FrictionTerm", "PositionFriction", "PositionFrictionTerm",
           "PreslidingFriction", "StribeckFriction", "StribeckTerm", "_dahl_track",
           "mean_abs_tanh", "mean_tanh", "speed_scale", "Backlash", "DiskTerm",
           "RigidGapTerm", "ShaftCompliance", "_disk_track", "_gap_track", "two_mass_step",
           "Cogging", "CoggingTerm", "RippleTerm", "TorqueRipple", "LoadTorque",
           "LoadTorqueTerm"]
