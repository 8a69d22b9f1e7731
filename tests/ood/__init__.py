"""Tests of rotlearn.ood."""
