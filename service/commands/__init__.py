"""One module per ``vtolpose`` subcommand, each with ``add_parser(subparsers)`` and ``run(args)``;
the shared option helpers live in ``common`` (and the LIDAR's in ``lidar_options``)."""
