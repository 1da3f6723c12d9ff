"""Files in and out: sessions, JSON, PLUS sequences, device sets and results, phantom files.

Takes paths; gives checked models (sessions, phantoms, tracked sequences) or InputError naming the
file and the problem. Every file appears whole or not at all.
"""
