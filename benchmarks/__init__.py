"""Throughput benchmarks: scripts that print a markdown table and write JSON."""
