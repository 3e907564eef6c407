"""Tests of mi_tetvr.render."""
