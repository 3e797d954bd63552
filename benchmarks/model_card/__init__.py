"""Write the model card (``docs/models.md``) of an exported model directory.

``python -m benchmarks.model_card --model geonet_infer/models/small_synth --synth-dir data/synth40
--prepared-dir data/synth40_prepared --kitti ../shared/realdata/kitti_raw_2011_09_26_sfnd
--out docs/models.md [--json OUT.json] [--before DIR] [--real REAL.json] [--from-json OUT.json]``

Every number comes from this run: the graphs run through the runtime (``Predictor``) in FP32 and INT8,
scored by the code of ``geonet-infer eval`` (:mod:`geonet_infer.eval`) beside its baselines, on the
synthetic held-out sequences (never trained on) and the KITTI frames with Velodyne ground truth (also
scaled by the camera height, 1.65 m). ``--real`` renders ``python -m benchmarks.eval_all --json`` (refused
unless measured on these graph files); ``--before DIR`` scores the previously shipped model in the same
run; ``--experiment/--teacher/--stop`` add the experiments' sections (each drawn by its own module in
``experiments/``). The headline numbers also go into the manifest's ``model_card`` (``--no-manifest``
skips it), which ``info`` shows and ``predict`` reads to warn about a synthetic-only model.
``--from-json`` renders again without measuring. Random-init models are refused unless
``--allow-random-init``. Bad input: one line naming the path, exit 2.

Modules: :mod:`.measure` (the runs), :mod:`.tables` and :mod:`.render` (the Markdown), :mod:`.cli`.
"""
