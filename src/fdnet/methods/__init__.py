"""Trained methods, one package each: ``fdnet`` (the paper's method), ``calc`` and ``netvlad``.

Every package holds its ``config`` (dataclasses written to ``RUN_DIR/config.yaml``, and
``PRESETS``), ``model`` (the networks), ``descriptor`` (inference: a run directory -> vectors) and
``training`` (its step on the shared loop in :mod:`fdnet.training.loop`, and ``train``). Which
packages there are is the method registry's (:mod:`fdnet.descriptors.registry`, the entries with
a trainer); inference modules never import ``training``, and importing this module is cheap.
"""

from __future__ import annotations

from pathlib import Path

from fdnet.errors import ConfigError


def trained_packages() -> dict[str, str]:
    """Trained method name -> its package (from the registry)."""
    from fdnet.descriptors.registry import all_specs

    return {s.name: s.package for s in all_specs() if s.trained}


def load_method_config(run_dir, cls, method: str):
    """Read a baseline run's config into ``cls``, first checking that the run directory holds a run
    of ``method`` (a CALC run given to NetVLAD is an error that says so)."""
    from fdnet import runs

    run_dir = Path(run_dir)
    if runs.is_run(run_dir):
        # which method made a run is answered in one place (runs.recorded_method)
        saved_method = runs.recorded_method(run_dir)
        if saved_method != method:
            path = runs.latest_checkpoint(run_dir) / runs.CONFIG_FILE
            what = f"a {saved_method!r} run" if saved_method else "not a readable run"
            raise ConfigError(
                f"{path}: is {what}, not a {method} run; give --checkpoint the --out folder "
                f"of `fdnet train {method}`"
            )
    return runs.load_config(run_dir, cls)
