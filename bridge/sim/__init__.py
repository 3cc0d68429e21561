"""`hilbo sim` and the virtual-device wiring: the only part of bridge that imports virtual_hw."""
