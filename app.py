"""volcap command line: `python app.py run graphs/demo.yaml` (see `python app.py --help`)."""
import sys

from nodegraph.cli import main

if __name__ == "__main__":
    sys.exit(main())
