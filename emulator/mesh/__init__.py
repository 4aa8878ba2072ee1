"""Meshes (files, generated, from a skin description) and the whole skin stepped in virtual time."""
