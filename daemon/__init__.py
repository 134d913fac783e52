"""cgamap.daemon."""
