"""cgamap.calib."""
