"""Tests of mi_tetvr.recon."""
