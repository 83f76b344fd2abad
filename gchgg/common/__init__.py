"""The bottom layer: checks, atomic checksummed files, the table of moved modules; imports nothing of gchgg."""
