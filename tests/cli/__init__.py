"""Tests of rotlearn.cli."""
