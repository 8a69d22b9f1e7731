"""Tests of rotlearn.bingham."""
