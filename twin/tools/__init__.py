"""Tools over the kernel: planner and scheduler benches, the driver scaffold, driver test helpers."""
