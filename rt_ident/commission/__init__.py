"""Commissioning a real axis before the host closes a loop on it (``rt-ident commission``)."""
