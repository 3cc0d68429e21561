"""Lab Streaming Layer: breaths from an LSL stream (``[cart] transport = "lsl"``).

Many labs (and HIL_toolkit) put the cart's breaths on LSL: one sample per breath, one channel
per quantity, named by the stream's ``<channels><channel><label>`` metadata. This transport
resolves the stream by name and/or type, maps the channel labels to the breath fields
(:data:`DEFAULT_LABELS`, or the ``channels`` option), and re-encodes every sample as a
hilbo-line (sequence number per sample, CRC), so the same parser and validator as every other
transport count its rejects (a NaN channel is a ``non_finite`` reject, not a crash). The breath
time is the time channel when the stream has one, else the sample's LSL time stamp.

LSL finds streams by multicast. To keep it on one PC (tests; a cart gateway on the same PC) use
an ``lsl_api.cfg`` with ``[multicast] ResolveScope = machine`` and ``[ports] IPv6 = disable``
and point the ``LSLAPICFG`` environment variable at it (drivers/cart/FORMAT.md, section 4).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

from msgspec import Meta

from drivers.cart._options import check_declared, check_keys, check_mapping, text
from drivers.cart.line import encode_line
from drivers.cart.transport import CartTransport, TransportHooks
from drivers.cart.validate import SEQ_MODULUS
from drivers.cart.vendors._table import FIELDS, REQUIRED_FIELDS, normalize_name
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

__all__ = ["DEFAULT_LABELS", "LslOptions", "LslTransport"]

DEFAULT_LABELS: Mapping[str, tuple[str, ...]] = {
    "t_s": ("t_s", "t", "time", "breath_time"),
    "vo2_ml_min": ("vo2_ml_min", "vo2"),
    "vco2_ml_min": ("vco2_ml_min", "vco2"),
    "ve_l_min": ("ve_l_min", "ve"),
    "rer": ("rer", "rq", "r"),
    "hr_bpm": ("hr_bpm", "hr", "hf"),
}
"""Channel labels recognised per field (compared lower-case, without spaces or quotes)."""

_LITRES = {"l/min", "lpm"}


@dataclass(frozen=True, slots=True)
class LslOptions:
    """Options of the ``"lsl"`` transport.

    Attributes:
        stream_name: The stream's name (``StreamInfo.name``); None matches any name.
        stream_type: The stream's content type; None matches any type. At least one of the two.
        resolve_timeout_s: How long to look for the stream when opening (fails after it).
        channels: Field -> channel label, for labels :data:`DEFAULT_LABELS` does not know
            (e.g. ``{vo2_ml_min = "VO2 [mL/min]"}``).
        poll_interval_s: Wait between polls of the inlet when no sample is waiting.
        max_line_bytes: Longest re-encoded line kept.
    """

    stream_name: str | None = None
    stream_type: str | None = None
    resolve_timeout_s: Annotated[float, Meta(gt=0.0, le=600.0)] = 5.0
    channels: Mapping[str, str] = field(default_factory=dict)
    poll_interval_s: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.02
    max_line_bytes: Annotated[int, Meta(ge=64)] = 256

    def __post_init__(self) -> None:
        if self.stream_name is None and self.stream_type is None:
            raise DriverConfigError("stream_name and stream_type are both unset: give at least one")
        for name in ("stream_name", "stream_type"):
            if getattr(self, name) is not None:
                text(getattr(self, name), name)
        check_declared(self)
        # stream_name/stream_type (at least one) and the channel table: checked here.
        channels = check_mapping(self.channels, "channels")
        check_keys(channels, FIELDS, "channels")
        for key, label in channels.items():
            text(label, f"channels.{key}")
        object.__setattr__(self, "channels", dict(channels))


@dataclass(frozen=True, slots=True)
class _Channel:
    index: int
    factor: float = 1.0


class LslTransport(CartTransport):
    """Samples of an LSL stream as hilbo-lines (see the module docstring)."""

    name = "lsl"

    def __init__(self, options: LslOptions, hooks: TransportHooks | None = None) -> None:
        super().__init__(max_line_bytes=options.max_line_bytes, backoff=None, hooks=hooks)
        self.options = options
        self._inlet: Any = None
        self._map: dict[str, _Channel] = {}
        self._seq = 0

    def describe(self) -> str:
        o = self.options
        parts = [f"name={o.stream_name!r}" if o.stream_name else "",
                 f"type={o.stream_type!r}" if o.stream_type else ""]
        return "lsl " + " ".join(p for p in parts if p)

    async def _open_link(self) -> None:
        import pylsl  # imported here: only this transport needs liblsl

        o = self.options
        pred = " and ".join(
            f"{key}='{value}'" for key, value in (("name", o.stream_name), ("type", o.stream_type)) if value
        )
        # resolve_bypred blocks for up to the timeout: off the event loop.
        found = await asyncio.to_thread(pylsl.resolve_bypred, pred, 1, o.resolve_timeout_s)
        if not found:
            raise TimeoutError(f"no LSL stream with {pred} within {o.resolve_timeout_s:g} s "
                               "(is the outlet running? same LSLAPICFG ResolveScope?)")
        inlet = pylsl.StreamInlet(found[0], max_buflen=360, recover=True)
        try:
            info = await asyncio.to_thread(inlet.info, o.resolve_timeout_s)
        except pylsl.util.TimeoutError as err:
            inlet.close_stream()
            raise TimeoutError(f"LSL stream {pred}: no metadata within {o.resolve_timeout_s:g} s") from err
        try:
            self._map = self._channel_map(info)
            # Subscribe now: an inlet receives only samples pushed after its data connection.
            await asyncio.to_thread(inlet.open_stream, o.resolve_timeout_s)
        except BaseException:
            inlet.close_stream()
            raise
        self._inlet = inlet

    def _channel_map(self, info: Any) -> dict[str, _Channel]:
        labels: list[str] = []
        units: list[str] = []
        ch = info.desc().child("channels").child("channel")
        for _ in range(info.channel_count()):
            labels.append(ch.child_value("label"))
            units.append(ch.child_value("unit"))
            ch = ch.next_sibling()
        norm = [normalize_name(label) for label in labels]
        out: dict[str, _Channel] = {}
        for f in FIELDS:
            wanted = ((normalize_name(self.options.channels[f]),) if f in self.options.channels
                      else DEFAULT_LABELS[f])
            index = next((norm.index(w) for w in wanted if w in norm), None)
            if index is None:
                if f in self.options.channels or (f in REQUIRED_FIELDS and f != "t_s"):
                    raise DriverConfigError(
                        f"{self.describe()}: no channel labelled "
                        f"{' or '.join(repr(w) for w in wanted)} for {f}; the stream's channels are "
                        f"{labels!r} (map them with [cart.options.channels])"
                    )
                continue
            litres = f in ("vo2_ml_min", "vco2_ml_min") and normalize_name(units[index]) in _LITRES
            out[f] = _Channel(index, 1000.0 if litres else 1.0)
        return out

    async def _read_chunk(self) -> bytes | None:
        import pylsl

        if self._inlet is None:
            raise ConnectionResetError("LSL inlet is closed")
        while True:
            try:
                samples, stamps = self._inlet.pull_chunk(timeout=0.0)
            except pylsl.util.LostError as err:
                raise ConnectionResetError(f"{self.describe()}: stream lost") from err
            if samples:
                return b"".join(self._encode(s, t) for s, t in zip(samples, stamps, strict=True))
            await asyncio.sleep(self.options.poll_interval_s)

    def _encode(self, sample: list[float], stamp: float) -> bytes:
        def value(f: str) -> float | None:
            ch = self._map.get(f)
            if ch is None:
                return None
            return float(sample[ch.index]) * ch.factor

        t, vo2, vco2 = value("t_s"), value("vo2_ml_min"), value("vco2_ml_min")
        record = BreathRecord(
            t_s=float(stamp) if t is None else t,
            vo2_ml_min=math.nan if vo2 is None else vo2,
            vco2_ml_min=math.nan if vco2 is None else vco2,
            ve_l_min=value("ve_l_min"),
            rer=value("rer"),
            hr_bpm=value("hr_bpm"),
        )
        line = encode_line(record, self._seq)
        self._seq = (self._seq + 1) % SEQ_MODULUS
        return line

    async def _close_link(self) -> None:
        inlet, self._inlet = self._inlet, None
        if inlet is not None:
            inlet.close_stream()
