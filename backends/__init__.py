"""Backbone families (installed as ``controlgs_adapter.backends``)."""
