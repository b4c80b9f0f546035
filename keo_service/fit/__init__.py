"""Identification from recorded data: the delay between the streams, the residual analysis
and its effects, and accuracy against a known truth. Built on `core` only; no I/O."""
