"""The application layer: ``runner`` (a scene run to a USD file, as ``warpspring run`` does it) and ``cli``
(the ``warpspring`` command). It may import every layer below it (core, io, analysis); nothing below imports
it."""
