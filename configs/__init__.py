"""Bundled configuration presets (TOML), installed as esmm.configs."""
