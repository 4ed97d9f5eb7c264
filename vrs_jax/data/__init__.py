"""Data stage: the Scene structure, dataset readers, image I/O, the embedded synthetic scene."""
