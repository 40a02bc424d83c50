"""Drives: one small protocol (base.py), families found by name (registry.py)."""
