"""Figures of the seed's chapter 6 (matplotlib, Agg backend): one module per family of figure.

Figures are made from results, never inside processing."""
