"""bridge: the asyncio process (wiring, safety supervision, MCAP logging, resume, CLI)."""

__all__: list[str] = []
