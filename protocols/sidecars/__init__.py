"""Packaged sidecar files: nominal raw-count conversions of known units (TOML)."""
