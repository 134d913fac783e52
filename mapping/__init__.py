"""cgamap.mapping."""
