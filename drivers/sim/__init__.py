"""cgamap.drivers.sim."""
