"""The exosuit's rated force: what its actuators are built to deliver.

It is the default of the config's ``[limits] rated_force_n``, and a ``max_force_n`` above the
rating is refused when the config loads (the device would refuse such tables, nack
``out_of_limits``, or, worse, be driven beyond its rating): a lab lowers the limit freely and
raises the rating only to its own device's.
"""

from __future__ import annotations

__all__ = ["RATED_FORCE_N"]

RATED_FORCE_N = 600.0
"""Rated (largest continuous) cable force of one actuator, N.

Source: the device this protocol was written for has no published rating in this repository;
600 N is the hardware limit the virtual exosuit enforces (``virtual_hw.exosuit.DeviceLimits``:
≈ 60 % of the body weight of a 100 kg wearer, Kim et al. 2019's largest ankle assistance). It is
the default of the config's ``[limits] rated_force_n``: a lab with another device sets that key to
its device's rating."""
