"""Test doubles and fixtures' building blocks used by the tests and the demo, not by the library's stages: the tiny
scene (:mod:`.tiny_scene`) and the ground-truth oracle detector (:mod:`.oracle`)."""
