"""Iso-Dream world models as TorchRL modules."""

__version__ = "0.1.0"
