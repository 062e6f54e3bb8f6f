"""Operator view (paper 000 section VI-B): pan-scan estimation, compensation geometry, rendering, web page."""
