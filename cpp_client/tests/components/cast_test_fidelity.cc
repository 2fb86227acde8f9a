// cast_test_fidelity: writes or checks the canonical cast.testing.RichEntry
// of the cross-language type-fidelity tests (tests/interop/test_cpp_fidelity.py
// builds the same value in Python; keep the two in step).
//
// args: {"mode": "write", "id": ID}  adds the canonical value as ID;
//       {"mode": "check", "id": ID}  reads ID and compares it with the
//       canonical value field by field; exit code 1 and the differences on
//       stdout if they differ.
// Prints one JSON line with the result, then stops.
#include <google/protobuf/util/message_differencer.h>

#include <iostream>
#include <limits>

#include "cast/cast.h"
#include "cast_fidelity.pb.h"
#include "probe_json.h"

namespace {

using cast::testing::RichEntry;

void point(RichEntry::Point* p, double x, double y, double z) {
  p->set_x(x);
  p->set_y(y);
  p->set_z(z);
}

RichEntry canonical() {
  RichEntry e;
  e.set_text("Gr\u00fc\u00dfe, \u4e16\u754c! \U0001F916 \u2014 \u00e7a va? \u03a9\u03bc\u03ad\u03b3\u03b1");
  std::string blob;
  for (int i = 0; i < 256; ++i) blob.push_back(static_cast<char>(i));
  e.set_blob(blob);
  e.set_int32_value(std::numeric_limits<std::int32_t>::min());
  e.set_int64_min(std::numeric_limits<std::int64_t>::min());
  e.set_int64_max(std::numeric_limits<std::int64_t>::max());
  e.set_uint32_value(std::numeric_limits<std::uint32_t>::max());
  e.set_uint64_max(std::numeric_limits<std::uint64_t>::max());
  e.set_sint64_value(-1234567890123456789LL);
  e.set_fixed64_value(std::numeric_limits<std::uint64_t>::max());
  e.set_sfixed64_value(std::numeric_limits<std::int64_t>::min());
  e.set_double_value(3.141592653589793);
  e.set_double_tiny(std::numeric_limits<double>::denorm_min());
  e.set_double_huge(std::numeric_limits<double>::max());
  e.set_double_infinity(-std::numeric_limits<double>::infinity());
  e.set_float_value(0.1f);
  e.set_flag(true);
  e.set_colour(RichEntry::COLOUR_BLUE);
  e.set_shade(cast::testing::SHADE_DARK);
  point(e.mutable_origin(), 1.25, -2.5, 1e-10);

  auto* region = e.mutable_region();
  region->set_label("zone \u00c4");
  point(region->add_outline(), 1, 2, 3);
  point(region->add_outline(), 4, 5, 6);
  region->set_colour(RichEntry::COLOUR_GREEN);
  (*region->mutable_attributes())["\u03ba\u03bb\u03b5\u03b9\u03b4\u03af"] = "\u03c4\u03b9\u03bc\u03ae";
  (*region->mutable_attributes())["empty"] = "";
  auto* child = region->add_children();
  child->set_label("inner");
  child->set_colour(RichEntry::COLOUR_RED);

  for (const char* tag : {"\u03b1", "", "tag with spaces", "\u65e5\u672c"}) e.add_tags(tag);
  for (std::int64_t s : {std::numeric_limits<std::int64_t>::min(), std::int64_t{-1}, std::int64_t{0}, std::int64_t{1},
                         std::numeric_limits<std::int64_t>::max()}) {
    e.add_samples(s);
  }
  for (double w : {0.1, 2.5e300, -7.0}) e.add_weights(w);
  e.add_colours(RichEntry::COLOUR_RED);
  e.add_colours(RichEntry::COLOUR_BLUE);
  e.add_colours(RichEntry::COLOUR_UNSPECIFIED);
  e.add_regions()->set_label("a");
  auto* b = e.add_regions();
  b->set_label("b");
  point(b->add_outline(), 1, 0, 0);

  (*e.mutable_counts())["one"] = 1;
  (*e.mutable_counts())["min"] = std::numeric_limits<std::int64_t>::min();
  (*e.mutable_counts())["max"] = std::numeric_limits<std::int64_t>::max();
  (*e.mutable_counts())["\u00fcn\u00ef"] = -5;
  point(&(*e.mutable_points())[-1], 1, 0, 0);
  (*e.mutable_points())[0];  // an empty message value
  point(&(*e.mutable_points())[std::numeric_limits<std::int64_t>::max()], 0, 0, 3);
  (*e.mutable_flags())[true] = "yes";
  (*e.mutable_flags())[false] = "no";

  auto* polygon = e.mutable_polygon();  // the oneof member this value sets
  polygon->set_label("tri");
  point(polygon->add_outline(), 0, 0, 0);
  point(polygon->add_outline(), 1, 0, 0);
  point(polygon->add_outline(), 0, 1, 0);
  e.set_maybe(0);  // present although 0: proto3 optional
  return e;
}

class Fidelity : public cast::UnmanagedComponent {
 public:
  void configure(const cast::Args& args) override {
    mode_ = args.getString("mode");
    id_ = args.getString("id");
    if ((mode_ != "write" && mode_ != "check") || id_.empty()) {
      throw cast::InvalidArgumentError("args must be {\"mode\": \"write\"|\"check\", \"id\": ID}");
    }
  }

  void run() override {
    cast::probe::Object out;
    if (mode_ == "write") {
      auto r = add(id_, canonical());
      out.boolean("ok", true).str("written", id_).unum("revision", r.revision);
      std::cout << out.json() << std::endl;
      requestStop();
      return;
    }
    RichEntry got = get<RichEntry>(id_);
    std::string report;
    google::protobuf::util::MessageDifferencer differ;
    differ.ReportDifferencesToString(&report);
    bool equal = differ.Compare(canonical(), got);
    // Presence is not part of MessageDifferencer's equality for every
    // version; check what proto3 optional and the oneof promise explicitly.
    if (!got.has_maybe()) {
      equal = false;
      report += "maybe: lost its presence\n";
    }
    if (got.has_never()) {
      equal = false;
      report += "never: present although never set\n";
    }
    if (got.shape_case() != RichEntry::kPolygon) {
      equal = false;
      report += "shape: oneof case " + std::to_string(got.shape_case()) + ", not polygon\n";
    }
    out.boolean("ok", equal).str("checked", id_).str("differences", report).message("value", got);
    std::cout << out.json() << std::endl;
    requestStop();
    if (!equal) throw cast::InvalidArgumentError("RichEntry '" + id_ + "' differs from the canonical value:\n" + report);
  }

 private:
  std::string mode_;
  std::string id_;
};

}  // namespace

CAST_COMPONENT_MAIN(Fidelity)
