/* test fixture: the version lines apply.py reads */
#ifndef SHORT_BUILD_VERSION
  #define SHORT_BUILD_VERSION "bugfix-2.1.x"
#endif
