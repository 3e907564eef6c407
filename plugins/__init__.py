"""Mitsuba-facing plugins of mi_tetvr (thin wrappers over the engine)."""
