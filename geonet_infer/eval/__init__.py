"""Evaluation: dataset layouts (``datasets/``), the paper's metrics, the scoring loops behind
``geonet-infer eval``, the classical baselines, Velodyne and stereo ground truth.

Not on the runtime's import path: ``import geonet_infer`` and ``geonet-infer predict`` load none of it.
"""
