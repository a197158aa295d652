"""What several test modules share that is not a pytest fixture: the repository's paths,
the pretend lab, fault sessions, small runs, the browser check, recorded devices. Test modules
import from here, never from each other; fixtures are in tests/conftest.py."""
