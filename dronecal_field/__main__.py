from dronecal_field.cli import main

raise SystemExit(main())
