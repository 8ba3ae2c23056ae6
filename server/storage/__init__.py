"""What the server keeps on disk: fitted rigs, performer profiles, and safe extraction of
uploaded archives.
"""
