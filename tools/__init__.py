"""Developer tools that read the source: the house in numbers (house_stats) and the import-linter
contract that keeps private names private (private_names). Not part of the installed package."""
