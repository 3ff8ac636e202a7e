"""Brasidas: a control stack for unmanned ground vehicles."""

__version__ = "0.1.0"
