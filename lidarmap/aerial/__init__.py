"""The aerial pipeline: tiles + footprints -> per-building points (prep) -> segmentation (``lidarmap.segment``) ->
densify / flatten -> voxels -> meshes (``pipeline`` runs it end to end; ``eval`` scores it against the simulator).

Stages take and return arrays or small dataclasses; files are read and written by ``lidarmap.io`` and the pipeline.
"""
