"""Input and output: ``scene`` (TOML scene files), ``usd`` (streaming USD writer), ``render`` (PNG frames
of a USD file) and ``runner`` (a scene run to a USD file, as ``warpspring run`` does it)."""
