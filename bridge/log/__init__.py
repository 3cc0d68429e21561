"""The session log: typed records (records), the MCAP writer (writer), readers (reader)."""

from __future__ import annotations

from bridge.log.errors import LogError, LogFormatError, LogStateError, LogValueError, LogWriteError
from bridge.log.records import (
    CHANNELS,
    EVENT_LEVELS,
    FORMAT_VERSION,
    METADATA_NAME,
    READABLE_VERSIONS,
    RECORD_TYPES,
    ChannelSpec,
    EventLevel,
    Topic,
    event_level,
)
from bridge.log.writer import (
    DEFAULT_FILE_MODE,
    LogStats,
    SessionLog,
    check_message,
    hilbo_version,
    new_session_id,
)

__all__ = [
    "CHANNELS",
    "DEFAULT_FILE_MODE",
    "EVENT_LEVELS",
    "FORMAT_VERSION",
    "METADATA_NAME",
    "READABLE_VERSIONS",
    "RECORD_TYPES",
    "ChannelSpec",
    "EventLevel",
    "LogError",
    "LogFormatError",
    "LogStateError",
    "LogStats",
    "LogValueError",
    "LogWriteError",
    "SessionLog",
    "Topic",
    "check_message",
    "event_level",
    "hilbo_version",
    "new_session_id",
]
