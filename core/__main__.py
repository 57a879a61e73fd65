from drivegain.cli import main

raise SystemExit(main())
