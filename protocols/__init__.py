"""Protocol files (TOML) and the landmark catalogue shipped with pelvislab; data only."""
