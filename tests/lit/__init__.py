"""Tests of rotlearn.lit."""
