"""Tests of mi_tetvr.mesh."""
