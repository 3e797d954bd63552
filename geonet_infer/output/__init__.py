"""What ``predict`` writes: the layout of its folder (``layout``), the frame writer, point clouds,
the result video, and :func:`~geonet_infer.output.predict.predict_to_dir` that runs a sequence into
it. Not loaded by ``import geonet_infer``.
"""
