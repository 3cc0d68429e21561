"""virtual_hw: the simulated wearer, virtual metabolic cart and virtual exosuit node."""

__all__: list[str] = []
