"""``geonet-infer convert``: the authors' released TensorFlow checkpoints -> a model directory, with
numpy and onnxruntime alone (no torch, no TensorFlow; INT8 adds onnx, the ``[convert]`` extra).

- :mod:`.tf_checkpoint` reads the checkpoint (the ``.index`` table, the ``.data-*`` shards, crc32c);
- :mod:`.official` knows the releases: which network is which, the official variable list;
- :mod:`.templates` holds the architecture templates and the recipe of each graph's weights;
- :mod:`.onnx_writer` writes a graph from a template and the computed weights;
- :mod:`.build` writes the whole directory (manifest, sha256, INT8 via :mod:`.int8`) and publishes it;
- :mod:`.verify` compares the graphs with the official forward pass in TensorFlow, where installed.

``python -m export --from-tf`` (repository, torch) runs the same :func:`.build.convert`.
"""
