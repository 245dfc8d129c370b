"""Tests of the Robotiq FT 300 driver (a package, so its test module names cannot clash with other drivers')."""
