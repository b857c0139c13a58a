"""Input and output: ``scene`` (TOML scene files), ``usd`` (streaming USD writer), ``usd_mesh`` (meshes read
from USD) and ``render`` (PNG frames of a USD file)."""
