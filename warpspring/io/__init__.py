"""Readers and writers: scene files (``scene``: the file and its loader; ``scene_schema``: the tables and
keys; ``scene_checks``: a parsed file checked against them; ``scene_build``: a scene's tables as builder
calls), USD output (``usd``: the writer; ``usd_prims``: the prims it authors; ``usd_stream``: the file's
life as frames stream in) and ``render`` (PNG frames of a USD file). Meshes read for the builder live below
it, in ``core.mesh_files``."""
