"""Runs ``python -m agents.experiments.<this file's name>`` from a checkout (``--help``)."""

if __name__ == "__main__":
    __import__("_checkout").run(__file__)
