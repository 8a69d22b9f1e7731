"""Tests of rotlearn.data."""
