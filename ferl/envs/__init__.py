"""Batched environments: every run of a batch has its own copy, advanced by one tensor op."""
