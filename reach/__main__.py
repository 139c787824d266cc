from reach.cli import console_main

console_main()
