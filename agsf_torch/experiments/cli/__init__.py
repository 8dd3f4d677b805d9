"""The ``agsf`` command: its parser and entry point (:mod:`.main`), one function per subcommand
(:mod:`.commands`) and what it shows on the terminal (:mod:`.terminal`)."""
