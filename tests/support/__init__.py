"""Test doubles and drivers shared by the tests and the benchmarks (not part of probecal)."""
