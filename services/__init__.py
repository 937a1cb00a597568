"""magnet's processes and command line: Zenoh sessions, signals, logging, argument parsing, files and SQLite."""
