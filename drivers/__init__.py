"""cgamap.drivers."""
