from edgerecon.cli import main

raise SystemExit(main())
