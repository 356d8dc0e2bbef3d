"""Competency of a controller on dm_control's point_mass, an env this project did not write:
the library used as a new user would, through its public API only (``main.py`` runs it)."""
