"""The pages a browser opens: ``/``, ``/viewer``, ``/overlay``, ``/perform``, ``/docs``, and
their built files.
"""
