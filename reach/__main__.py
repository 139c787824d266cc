from reach.cli import main

raise SystemExit(main())
