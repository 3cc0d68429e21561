"""hilbo_core: the pure algorithms of hilbo (exports land with the modules)."""

__all__: list[str] = []
