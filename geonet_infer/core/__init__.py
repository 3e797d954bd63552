"""What ``load()`` runs: the manifest, graph inputs, the cascade over a sequence, the Predictor and
its results. Imports only ``engines/``, ``io/`` and the package's small shared modules (errors,
conventions, limits, tasks, check, classical); never ``output/``, ``batch/``, ``eval/`` or
``bench/`` (tests/runtime/test_import_contract.py)."""
