from agv_fe.cli import main

raise SystemExit(main())
