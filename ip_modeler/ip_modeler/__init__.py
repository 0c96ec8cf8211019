"""Implicit-polynomial surface fitting with adaptive degree by incremental QR (Eqs. 19-22)."""
