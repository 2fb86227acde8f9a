// CAST on gRPC, C++ client library: everything a component needs.
#pragma once

#include "cast/args.h"
#include "cast/basic_types.h"
#include "cast/component.h"
#include "cast/connect.h"
#include "cast/credentials.h"
#include "cast/errors.h"
#include "cast/filters.h"
#include "cast/grpc_transport.h"
#include "cast/loan.h"
#include "cast/log.h"
#include "cast/runner.h"
#include "cast/schemas.h"
#include "cast/types.h"
#include "cast/version.h"
#include "cast/views.h"
