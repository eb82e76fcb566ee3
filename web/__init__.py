"""Viser operator console (arrives with the console issue)."""
