"""The browser console (viser)."""
