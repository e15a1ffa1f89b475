"""Simulators: the fingertip scene simulator (FTIR video with exact ground truth) and a software twin of
every device, implementing the :mod:`drivers` interfaces and speaking the same bytes where there is a wire."""
