"""Training and export (needs the ``[train]`` extra: torch, onnx). Nothing outside this package imports torch."""
