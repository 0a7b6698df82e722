"""Recorded sources: they yield the same :class:`rig.types.Frame` a camera driver yields."""
