"""The command lines, argparse and nothing else: ``etar-bench`` (``bench``), ``etar``
(``etar``), the eight service programs (``roles``) and the Zenoh flags they share; each
parses and calls the wings below.  ``reference`` writes docs/cli.md from the parsers."""
