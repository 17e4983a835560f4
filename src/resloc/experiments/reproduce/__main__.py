"""``python -m resloc.experiments.reproduce --write-examples DIR``."""

from resloc.experiments.reproduce.orchestration import main

raise SystemExit(main())
