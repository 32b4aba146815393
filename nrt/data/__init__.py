"""Scenes, procedural media and skies, Mitsuba rendering and dataset I/O."""
