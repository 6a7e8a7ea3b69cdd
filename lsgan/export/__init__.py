"""Exporters that turn generated joint positions into files other tools read (BVH)."""
