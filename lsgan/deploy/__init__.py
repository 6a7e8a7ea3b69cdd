"""A generator run as ONNX graphs that run without torch (``lsgan export-model --onnx``, docs/deploy.md).

Modules, one per concept:

* :mod:`lsgan.deploy.manifest`: the exported folder's ``manifest.json`` (format, file hashes) and its reader;
* :mod:`lsgan.deploy.onnx_export`: the torch side: GAN generator, VAE decoder and MiniLM text encoder to ONNX;
* :mod:`lsgan.deploy.int8`: dynamic int8 quantisation of the graphs and its measured joint error;
* :mod:`lsgan.deploy.runtime`: onnxruntime + tokenizers + numpy: prompts or labels to motions.

Only ``onnx_export`` imports torch; this package and the others never do.
"""
