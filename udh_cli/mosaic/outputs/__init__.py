"""The files of a run: their names, and writing them so that they appear together or not at all."""
