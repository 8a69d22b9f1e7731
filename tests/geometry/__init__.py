"""Tests of rotlearn.geometry."""
