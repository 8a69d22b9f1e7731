"""Tests of rotlearn.nets."""
