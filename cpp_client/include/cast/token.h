// The name of the tokens' header before the three client libraries got one
// file map (Python client/credentials.py, Java Credentials.java): peekToken,
// mintToken and the rest now live in cast/credentials.h. Kept so that code
// including it still compiles; include cast/credentials.h in new code.
#pragma once

#include "cast/credentials.h"
