"""Tests of rotlearn.heads."""
