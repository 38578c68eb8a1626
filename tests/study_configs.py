"""Tiny study configs for pipeline and CLI tests (seconds, not minutes)."""

from __future__ import annotations

from pathlib import Path

import yaml


def tiny_config(**overrides: object) -> dict:
    """A study on grids 8, 16, 32 that screens and estimates in about a second.

    ``overrides`` replace top-level sections (e.g. ``qoi={...}``).
    """
    config = {
        "schema_version": 1,
        "seed": 2026,
        "surface": {
            "system_size": 1.0,
            "wavenumbers": {"k_l": 1, "k_r": 2, "k_s": 8},
            "hurst": 0.8,
            "rms_height": 1.0,
        },
        "material": {"e_star": 1.0},
        "load": {"relative": 0.2},
        "solver": {"tol": 1e-8},
        "qoi": {"contact_area": {"unit": "percent", "tol": 2.0}},
        "grid": {"coarsest": 8, "max_level": 2},
        "screening": {"levels": 3, "samples": 8},
        "estimation": {"initial_samples": 4, "batch_size": 4},
    }
    config.update(overrides)
    return config


def write_config(path: Path, config: dict) -> Path:
    """Write ``config`` as YAML to ``path`` and return it."""
    path.write_text(yaml.safe_dump(config, sort_keys=False))
    return path
