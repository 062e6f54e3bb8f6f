"""Readers and writers of recorded data sets (file I/O at the edge; the algorithms never read files)."""
