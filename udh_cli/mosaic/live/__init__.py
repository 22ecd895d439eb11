"""Live mode: following a folder as frames arrive, the quick look, and the refreshed mosaics."""
