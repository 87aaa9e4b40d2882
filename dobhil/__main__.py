from dobhil.cli.main import main

raise SystemExit(main())
