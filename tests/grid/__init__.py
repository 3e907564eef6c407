"""Tests of mi_tetvr.grid."""
