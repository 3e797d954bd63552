"""Developer tools: benchmarks and the generators of docs/models.md, docs/results.md and docs/performance.md.

A package so that ``python -m benchmarks.model_card`` resolves to this folder whatever else is installed.
"""
