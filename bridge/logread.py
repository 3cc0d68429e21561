"""Compatibility name of :mod:`bridge.log.reader` (reading, damaged-file scanning, recovery)."""

from __future__ import annotations

from bridge.log.reader import (
    ChannelInfo,
    Damage,
    LogContents,
    LogMessage,
    RecoverReport,
    read_log,
    recover,
)

__all__ = ["ChannelInfo", "Damage", "LogContents", "LogMessage", "RecoverReport", "read_log", "recover"]
