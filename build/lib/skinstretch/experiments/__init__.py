"""Experiments: protocols, recording, playback, analysis and the ``skinstretch`` command line.

This is the only package that chooses real or simulated devices (from a rig file) and wires everything together.
"""
