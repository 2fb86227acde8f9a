package cast.client;

import com.google.protobuf.ByteString;
import com.google.protobuf.CodedOutputStream;
import com.google.protobuf.Descriptors.Descriptor;
import com.google.protobuf.Descriptors.FieldDescriptor;
import com.google.protobuf.Message;
import com.google.protobuf.WireFormat;
import java.io.IOException;
import java.io.UncheckedIOException;
import java.util.Locale;
import java.util.stream.Collectors;

/**
 * What a {@link Loan}'s payload follows: the value serialised (every field but the loaned one),
 * then the loaned field's key and length. Protobuf takes fields in any order, so header and
 * payload are an ordinary serialised message and the server needs nothing new. The twin of
 * {@code loan_header} in python/cast/client/loan.py.
 */
final class LoanHeader {
  /** The most a loan's value (header and payload) may be here: what one Java array holds, with room to spare. */
  static final long MAX_BYTES = Integer.MAX_VALUE - 1024;

  private LoanHeader() {}

  /**
   * The field of {@code value} named {@code field}, a loan of {@code size} bytes of which may be
   * taken; InvalidArgumentError, naming the field and what would do, when it is not a top-level
   * singular {@code bytes} field of the value's type, already holds bytes, or {@code size} is
   * negative.
   */
  static FieldDescriptor field(Message value, String field, int size) {
    if (value == null) {
      throw new InvalidArgumentError("entry values are protobuf messages, got null");
    }
    Descriptor type = value.getDescriptorForType();
    FieldDescriptor found = field == null ? null : type.findFieldByName(field);
    if (found == null) {
      String loanable =
          type.getFields().stream().filter(LoanHeader::loanable).map(FieldDescriptor::getName)
              .collect(Collectors.joining(", "));
      throw new InvalidArgumentError(
          type.getName() + " has no field '" + field + "': a loan is taken of one of its top-level bytes fields ("
              + (loanable.isEmpty() ? "it has none" : loanable) + ")");
    }
    if (!loanable(found)) {
      String kind = (found.isRepeated() ? "a repeated " : "a ") + found.getType().name().toLowerCase(Locale.ROOT);
      throw new InvalidArgumentError(
          "field '" + field + "' of " + type.getFullName() + " is " + kind
              + ": a loan is taken of a top-level singular bytes field");
    }
    int held = ((ByteString) value.getField(found)).size();
    if (held > 0) {
      throw new InvalidArgumentError(
          "field '" + field + "' of " + type.getFullName() + " already holds " + held
              + " bytes: leave it empty, the loan's buffer is its bytes");
    }
    if (size < 0) {
      throw new InvalidArgumentError("a loan's size is a number of bytes, 0 or more, not " + size);
    }
    if (value.getSerializedSize() + 16L + size > MAX_BYTES) {
      throw new InvalidArgumentError(
          "a loan of " + size + " bytes is over what one Java array holds with the rest of the value; the server"
              + " keeps values of at most limits.max_value_bytes (8 MiB by default): store large data elsewhere"
              + " and keep a reference");
    }
    return found;
  }

  private static boolean loanable(FieldDescriptor field) {
    return field.getType() == FieldDescriptor.Type.BYTES && !field.isRepeated();
  }

  /** The header of a loan of {@code size} bytes of {@code field}: {@code serialised}, its key, its length. */
  static ByteString of(ByteString serialised, FieldDescriptor field, int size) {
    byte[] tail =
        new byte[CodedOutputStream.computeTagSize(field.getNumber()) + CodedOutputStream.computeUInt32SizeNoTag(size)];
    CodedOutputStream out = CodedOutputStream.newInstance(tail);
    try {
      out.writeTag(field.getNumber(), WireFormat.WIRETYPE_LENGTH_DELIMITED);
      out.writeUInt32NoTag(size);
      out.checkNoSpaceLeft();
    } catch (IOException e) { // an array of the computed size: cannot happen
      throw new UncheckedIOException(e);
    }
    return serialised.concat(ByteString.copyFrom(tail));
  }
}
