"""The shipped configuration as package data: default.toml, camera/ rigs, scenarios/ (see app.files)."""
