"""``python -m latentsindy``: the command line (see ``latentsindy --help``)."""

if __name__ == "__main__":
    from latentsindy._cli.main import main

    raise SystemExit(main())
